"""Each benchmark script runs in --quick mode and writes its JSON and PNG.

The scripts run in the test process (as ``python script.py`` would, through
`runpy`): a subprocess per script would spend about 2 s of the suite's time
importing JAX, diffrax and matplotlib again.
"""

import json
import runpy
import sys
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import pytest

BENCH = Path(__file__).resolve().parent.parent / "benchmarks"


def _run(script: str, out: Path, repeats: bool = True, args=(), name=None) -> dict:
    extra = (["--repeats", "1"] if repeats else []) + list(args)
    argv, path = sys.argv, list(sys.path)
    sys.argv = [str(BENCH / script), "--quick", *extra, "--out", str(out)]
    sys.path.insert(0, str(BENCH))  # the scripts import _common from their folder
    try:
        runpy.run_path(str(BENCH / script), run_name="__main__")
    finally:
        sys.argv, sys.path[:] = argv, path
        plt.close("all")
    name = name or script.removesuffix(".py")
    js, png = out / f"{name}-quick.json", out / f"{name}-quick.png"
    assert js.is_file() and png.is_file()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not (out / f"{name}.json").exists()  # quick never writes the full names
    return json.loads(js.read_text())


@pytest.mark.slow
def test_work_precision_quick(tmp_path):
    res = _run("work_precision.py", tmp_path)
    assert res["env"]["backend"]
    for scene in res["scenes"].values():
        methods = {p["method"] for p in scene["points"]}
        assert {"RKMK4", "diffrax Tsit5", "SciPy RK45"} <= methods
        for p in scene["points"]:
            assert p["ok"] and p["run_s"] > 0 and p["fevals"] > 0
        # Errors shrink with the step / tolerance for every method.
        for m in methods:
            pts = [p for p in scene["points"] if p["method"] == m]
            if len(pts) > 1:
                assert pts[-1]["att_err"] < pts[0]["att_err"]
        lie = [p for p in scene["points"] if p["family"] == "lie"]
        assert max(p["orth_err"] for p in lie) < 1e-13


@pytest.mark.slow
def test_stability_quick(tmp_path):
    res = _run("stability.py", tmp_path)
    sd = res["stable_dt"]
    for label, dts in sd["max_dt"].items():
        assert len(dts) == len(sd["gains"])
        # Stiffer gains never allow a larger step.
        assert all(b <= a * 1.001 for a, b in zip(dts, dts[1:], strict=False)), label
    series = res["long_horizon"]["series"]
    assert series["RKMK4"]["max_orth_err"] < 1e-13
    assert series["diffrax RK4"]["final_orth_err"] > 100 * series["RKMK4"]["final_orth_err"]
    assert res["flips"]["reference_flips"] >= 1


@pytest.mark.slow
def test_throughput_quick(tmp_path):
    res = _run("throughput.py", tmp_path)
    rows = res["sweep"]["rows"]
    assert {r["dtype"] for r in rows} == {"float32", "float64"}
    assert all(r["finite"] and r["body_steps_per_s"] > 0 for r in rows)
    eq = res["equal_accuracy"]
    assert eq["rkmk4_err"] < 1e-7 and eq["tsit5_err"] < 1e-7
    assert eq["RKMK4"]["trajectories_per_s"] > 0 and eq["diffrax Tsit5"]["trajectories_per_s"] > 0


@pytest.mark.slow
def test_integrators_quick(tmp_path):
    res = _run("integrators.py", tmp_path)
    names = {r["method"] for r in res["methods"]}
    assert {"LieEuler", "RKMK4", "CF4", "LGVI"} <= names
    for r in res["methods"]:
        assert r["us_per_step"] > 0 and r["batch_body_steps_per_s"] > 0 and r["order"] >= 1
    assert res["layout"]["aos_updates_per_s"] > 0 and res["layout"]["soa_updates_per_s"] > 0


@pytest.mark.slow
def test_adaptive_quick(tmp_path):
    res = _run("adaptive.py", tmp_path)
    methods = {r["method"] for r in res["runs"]}
    assert any(m.startswith("lie-") for m in methods) and any("Tsit5" in m for m in methods)
    for r in res["runs"]:
        assert r["run_s"] > 0 and r["steps"] >= r["accepted"] > 0
        if r["method"].startswith("lie-"):
            assert r["orthogonality"] < 1e-13  # adaptive Lie runs stay on the group


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:dt = .* is beyond the stability limit")  # the script's sweep
def test_sweep_and_tune_quick(tmp_path):
    sweep = _run("sweep.py", tmp_path, repeats=False)
    assert {r["dtype"] for r in sweep["rows"]} == {"float64", "float32"}
    assert all(r["runs_per_second"] > 0 for r in sweep["rows"])
    tune = _run("tune.py", tmp_path, repeats=False)
    forward = [r for r in tune["rows"] if r["variant"] == "forward pass"]
    assert forward and all(r["time_ratio"] == 1.0 for r in forward)
    assert all(r["seconds"] > 0 for r in tune["rows"])
    # a user's own cost on saved runs: its forward pass is the baseline of its rows
    traj = _run("tune.py", tmp_path, False, ["--cost", "trajectory"], "tune-trajectory")
    assert [r["variant"] for r in traj["rows"]] == [
        "forward pass",
        "reverse (default)",
        "forward mode (jacfwd)",
    ]
    assert traj["rows"][0]["time_ratio"] == 1.0 and traj["benchmark"] == "tune-trajectory"


@pytest.mark.slow
def test_element_work_quick(tmp_path):
    """The counted work of a loop step: the gradient's (two tangent columns over one
    primal) between 1.5x and 4x the forward pass's, both found (nonzero)."""
    data = _run("element_work.py", tmp_path, False, name="element-work")
    fwd, grad = data["rows"]
    assert fwd["variant"] == "forward pass" and fwd["step_work"] > 0
    assert 1.5 < grad["work_ratio"] < 4


@pytest.mark.slow
def test_difftune_quick(tmp_path):
    data = _run("difftune.py", tmp_path)
    rmse = data["rmse_history"]
    assert len(rmse) == 11 and rmse[-1] < rmse[0]  # 10 iterations of descent
    assert data["gradient_forward_reverse_agreement"] is None  # quick: no reverse mode
    assert list(data["timings"]) == ["forward pass"]  # quick: no gradient timings
    assert data["timings"]["forward pass"]["run_s"] > 0 and data["tune_wall_s"]["forward"] > 0
    assert min(min(v) for v in data["gains_final"].values()) >= 0.5


@pytest.mark.slow
def test_shared_reference_quick(tmp_path):
    res = _run("shared_reference.py", tmp_path)
    rows = res["rows"]
    assert {(r["batch"], r["Rd"]) for r in rows} == {
        (b, rd)
        for b in ("vmap(simulate) over gain pairs", "expected_cost over starts")
        for rd in ("shared", "per run")
    }
    for r in rows:
        assert r["body_steps_per_s"] > 0 and r["speedup"] > 0
        assert r["max_diff_vs_per_run"] < 1e-12  # the same numbers either way


@pytest.mark.slow
def test_emitters_quick(tmp_path):
    sys.path.insert(0, str(BENCH))  # the script imports _common from its folder
    try:
        supported = runpy.run_path(str(BENCH / "emitters.py"), run_name="emitters")[
            "option_supported"
        ]()
    finally:
        sys.path.remove(str(BENCH))
    if not supported:
        pytest.skip("this jaxlib's XLA has no emitter option to compare (JAX 0.11 and later)")
    res = _run("emitters.py", tmp_path)
    assert res["settings"]["older IR emitters"] == {"xla_cpu_use_fusion_emitters": False}
    names = [r["program"] for r in res["rows"]]
    assert any("grad" in n for n in names) and any("quadrotor" in n for n in names)
    for r in res["rows"]:
        assert r["default_compile_s"] > 0 and r["older_compile_s"] > 0
        assert r["default_run_s"] > 0 and r["older_run_s"] > 0
        assert r["max_rel_diff"] < 1e-9  # the same program, to round-off


def test_startup_quick(tmp_path):
    """A fresh process builds the seed scene with a handful of compiled programs.

    Built operation by operation, `scenes.seed()` compiled 29 XLA programs on its first
    call in a process (1.6 s on the 2-core CPU); jitted cores and NumPy for concrete
    constants leave three (the Euler angles, the inertia, the initial state).
    """
    res = _run("startup.py", tmp_path)
    (row,) = res["rows"]
    assert (row["entry"], row["code"]) == ("scenes.seed()", "current")
    assert 1 <= row["compiles"] <= 4, row
    assert row["cold_s"] > 0 and row["warm_s"] > 0 and row["import_s"] > 0


def test_allocator_quick(tmp_path):
    """Each setting's child process sees its own allocator variables, and the ratios are
    taken within a setting (derivative / forward pass) and across (kept / defaults)."""
    res = _run("allocator.py", tmp_path)
    kept = res["settings"]["buffers kept"]
    assert kept["MALLOC_ARENA_MAX"] == "1" and res["settings"]["glibc defaults"] == {}
    rows = {(r["setting"], r["derivative"]): r for r in res["rows"]}
    assert set(rows) == {(s, d) for s in res["settings"] for d in ("forward", "grad")}
    for (setting, derivative), r in rows.items():
        assert r["seen"] == (kept if setting == "buffers kept" else {}), r["seen"]
        assert r["seconds"] > 0 and r["temp_bytes"] > 0
        fwd = rows[(setting, "forward")]["seconds"]
        assert r["forward_ratio"] == pytest.approx(r["seconds"] / fwd)
        base = rows[("glibc defaults", derivative)]["seconds"]
        assert r["time_ratio"] == pytest.approx(r["seconds"] / base)


@pytest.mark.slow
def test_ablation_quick(tmp_path):
    """Each configuration compiles its own program: with every pass off a run compiles
    another program than with all, and computes the same numbers to round-off."""
    res = _run("ablation.py", tmp_path)
    rows = {(r["workload"], r["config"]): r for r in res["rows"]}
    assert set(rows) == {("run", "all passes"), ("run", "none")}
    base, none = rows[("run", "all passes")], rows[("run", "none")]
    assert base["ratio"] == 1.0 and base["same_program_as_base"]
    assert not none["same_program_as_base"] and none["passes_off"] == res["passes"]
    assert none["max_rel_diff"] < 1e-12
    for r in rows.values():
        assert r["run_s"] == r["run_s_range"][0] == min(r["rounds"]) > 0 and r["compile_s"] > 0
    # what a run cut off keeps: the finished workloads, in the final file's schema
    partial = json.loads((tmp_path / "ablation-quick.partial.json").read_text())
    assert partial["workloads"] == res["workloads"] and partial["rows"] == res["rows"]


def test_ablation_merge_replaces_the_workloads_measured_again(tmp_path):
    """``ablation.py --merge``: the workloads measured again replace their rows, the others
    are kept in their order, new ones come last, and ``merged`` names the environment of
    each; results with other configurations are refused."""
    sys.path.insert(0, str(BENCH))
    try:
        import ablation
    finally:
        sys.path.remove(str(BENCH))

    def rows(workload, tag):
        return [{"workload": workload, "config": c, "tag": tag} for c in ("all passes", "none")]

    configs = {"all passes": {}, "none": {}}
    old = {
        "configs": configs,
        "quick": False,
        "env": {"date": "old"},
        "workloads": {"run": {}, "grad": {}},
        "rows": rows("run", "old") + rows("grad", "old"),
    }
    path = tmp_path / "ablation.json"
    path.write_text(json.dumps(old))
    new = dict(old, env={"date": "new"}, workloads={"grad": {}, "large grad": {}})
    new["rows"] = rows("large grad", "new") + rows("grad", "new")
    out = ablation.merged(path, new)
    assert list(out["workloads"]) == ["run", "grad", "large grad"]
    assert [(r["workload"], r["tag"]) for r in out["rows"]] == [
        ("run", "old"),
        ("run", "old"),
        ("grad", "new"),
        ("grad", "new"),
        ("large grad", "new"),
        ("large grad", "new"),
    ]
    assert out["merged"] == {"grad": {"date": "new"}, "large grad": {"date": "new"}}
    assert out["env"] == {"date": "old"}
    with pytest.raises(ValueError, match="other configurations"):
        ablation.merged(path, dict(new, configs={"all passes": {}}))


@pytest.mark.slow
def test_vehicle_quick(tmp_path):
    """The plain quadrotor is the baseline of every ratio in its dtype, measured in the same
    rounds; the full vehicle compiles another program, and its runs stay finite."""
    res = _run("vehicle.py", tmp_path)
    rows = {(r["dtype"], r["config"]): r for r in res["rows"]}
    assert set(rows) == {("float32", "plain"), ("float32", "full vehicle")}
    plain, full = rows[("float32", "plain")], rows[("float32", "full vehicle")]
    assert plain["ratio"] == 1.0 and plain["same_program_as_plain"]
    assert not full["same_program_as_plain"]
    assert full["ratio"] == pytest.approx(full["run_s"] / plain["run_s"])
    assert len(full["rounds"]) == len(plain["rounds"]) == len(full["ratio_rounds"])
    for r in rows.values():
        assert r["run_s"] == min(r["rounds"]) > 0 and r["compile_s"] > 0
        assert r["body_steps_per_s"] == pytest.approx(res["batch"] * res["n_steps"] / r["run_s"])
        assert r["finite_fraction"] == 1.0 and r["layout"] in ("array", "scalarized")


def test_vehicle_figure_keeps_a_ratio_far_below_one_in_view(tmp_path, monkeypatch):
    """A quick run's ratio (one round of a tiny batch) can fall far below 1: its bar stays
    in view and the figure's layout holds, with no layout warning."""
    monkeypatch.syspath_prepend(str(BENCH))  # vehicle.py imports _common from its folder
    vehicle = runpy.run_path(str(BENCH / "vehicle.py"), run_name="vehicle")
    row = {"dtype": "float32", "config": "full vehicle", "ratio": 0.1, "ratio_range": [0.05, 0.2]}
    data = {
        "configs": {"plain": [], "full vehicle": []},
        "dtypes": ["float32"],
        "rows": [row],
        "env": {"backend": "cpu", "cpu_count": 2, "device_kind": "cpu"},
        "batch": 8,
        "n_steps": 10,
    }
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fig = vehicle["figure"](data)
        fig.savefig(tmp_path / "vehicle-quick.png", dpi=40)
    bottom = fig.axes[0].get_ylim()[0]
    plt.close(fig)
    assert bottom <= 0.05

"""Stale study results: a trial's stored values are refused on resume when the code it runs changed anywhere
(its own module, a module it imports, ocpkit, a user's problem file) or a numerical dependency's version did;
the refusal names what changed, and --reuse-stale / --rerun-stale decide."""

import os
import re
import textwrap
import time
from pathlib import Path

import pytest

from ocpkit.runs.study import StaleTrialsError, Study, code_hash, grid, run


def _module(folder: Path, name: str, text: str) -> Path:
    path = folder / f"{name}.py"
    path.write_text(textwrap.dedent(text))
    return path


def _touch_later(path: Path, text: str) -> None:
    """Rewrite ``path``; its modification time moves on even on a coarse-clock file system."""
    before = path.stat().st_mtime_ns
    path.write_text(text)
    if path.stat().st_mtime_ns == before:
        os.utime(path, ns=(before + 10**9, before + 10**9))


@pytest.fixture
def trial_folder(tmp_path, monkeypatch):
    """A folder on sys.path for the test's trial modules, and a log folder that counts trial executions."""
    folder = tmp_path / "mod"
    folder.mkdir()
    monkeypatch.syspath_prepend(str(folder))
    log = tmp_path / "log"
    log.mkdir()
    monkeypatch.setenv("STALE_TEST_LOG", str(log))
    return folder


def _executions() -> int:
    return len(os.listdir(os.environ["STALE_TEST_LOG"]))


_TRIAL = """
    import os, pathlib, time
    def trial(x):
        import {helper}   # imported inside the trial: a worker imports it when the trial runs
        pathlib.Path(os.environ["STALE_TEST_LOG"], f"{{x}}-{{time.time_ns()}}").touch()
        return {{"y": {helper}.FACTOR * x}}
"""


def test_a_change_in_a_module_the_trial_imports_is_refused_naming_it(trial_folder, tmp_path):
    helper = _module(trial_folder, "stale_helper_a", "FACTOR = 2\n")
    _module(trial_folder, "stale_trial_a", _TRIAL.format(helper="stale_helper_a"))
    import stale_trial_a

    study = Study("s", stale_trial_a.trial, grid(x=range(3)))
    out = tmp_path / "out"
    assert run(study, out, workers=1, progress=False).y.tolist() == [0, 2, 4]
    run(study, out, workers=1, progress=False)  # same code: nothing to refuse or redo
    assert _executions() == 3

    _touch_later(helper, "FACTOR = 3\n")  # the trial's own file is unchanged
    with pytest.raises(StaleTrialsError) as refused:
        run(study, out, workers=1, progress=False)
    message = str(refused.value)
    assert "3 of the 3 stored trials of study 's'" in message and "--reuse-stale" in message
    assert "changed stale_helper_a" in message and "stale_trial_a" not in message.split("(", 1)[1].split(")")[0]
    df = run(study, out, workers=1, progress=False, stale="reuse")  # the explicit way out: old values kept
    assert df.y.tolist() == [0, 2, 4] and _executions() == 3
    df = run(study, out, workers=1, progress=False, stale="rerun")
    assert df.y.tolist() == [0, 3, 6] and _executions() == 6
    run(study, out, workers=1, progress=False)  # current again
    assert _executions() == 6


def test_a_module_that_is_not_imported_does_not_make_trials_stale(trial_folder, tmp_path):
    _module(trial_folder, "stale_helper_b", "FACTOR = 2\n")
    bystander = _module(trial_folder, "stale_bystander_b", "X = 1\n")
    _module(trial_folder, "stale_trial_b", _TRIAL.format(helper="stale_helper_b"))
    import stale_trial_b

    study = Study("s", stale_trial_b.trial, grid(x=range(2)))
    run(study, tmp_path / "out", workers=1, progress=False)
    _touch_later(bystander, "X = 2\n")
    run(study, tmp_path / "out", workers=1, progress=False)  # not refused, not rerun
    assert _executions() == 2


def test_a_dependency_version_change_is_refused_naming_it(trial_folder, tmp_path, monkeypatch):
    from ocpkit.runs import provenance

    _module(trial_folder, "stale_helper_c", "FACTOR = 2\n")
    _module(trial_folder, "stale_trial_c", _TRIAL.format(helper="stale_helper_c"))
    import stale_trial_c

    study = Study("s", stale_trial_c.trial, grid(x=range(2)))
    run(study, tmp_path / "out", workers=1, progress=False)
    recorded = provenance.dependency_versions()
    assert set(recorded) == {"casadi", "numpy", "scipy", "proxsuite", "osqp", "daqp", "pin", "taichi", "control"}
    assert recorded["numpy"] is not None
    before = code_hash(stale_trial_c.trial)
    monkeypatch.setattr(provenance, "dependency_versions", lambda: {**recorded, "numpy": "99.0.0", "casadi": None})
    assert code_hash(stale_trial_c.trial) != before
    with pytest.raises(StaleTrialsError, match=r"2 of the 2 stored trials") as refused:
        run(study, tmp_path / "out", workers=1, progress=False)
    message = str(refused.value)
    assert f"numpy {recorded['numpy']} → 99.0.0" in message
    assert f"casadi {recorded['casadi']} → not installed" in message
    assert "changed" not in message and "scipy" not in message  # no code, and no other version, changed
    run(study, tmp_path / "out", workers=1, progress=False, stale="reuse")
    assert _executions() == 2


def test_a_changed_thread_count_or_taichi_setting_is_refused_naming_it(trial_folder, tmp_path, monkeypatch):
    """Variables that change results (BLAS and Taichi threads, TI_ARCH) mark finished trials stale; where files are
    kept (OCPKIT_CACHE_DIR, Taichi's kernel cache) does not."""
    from ocpkit.runs import provenance

    for name in provenance.environment():
        monkeypatch.delenv(name)
    _module(trial_folder, "stale_helper_f", "FACTOR = 2\n")
    _module(trial_folder, "stale_trial_f", _TRIAL.format(helper="stale_helper_f"))
    import stale_trial_f

    study, out = Study("s", stale_trial_f.trial, grid(x=range(2))), tmp_path / "out"
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    run(study, out, workers=1, progress=False)
    monkeypatch.setenv("OCPKIT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("TI_OFFLINE_CACHE_FILE_PATH", str(tmp_path / "kernels"))
    run(study, out, workers=1, progress=False)  # not refused, not rerun
    assert _executions() == 2
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setenv("TI_ARCH", "cpu")
    with pytest.raises(
        StaleTrialsError,
        match=r"2 of the 2 stored trials of study 's'.* were computed by other code "
        r"or settings \(OMP_NUM_THREADS 1 → 2; TI_ARCH unset → cpu\)",
    ):
        run(study, out, workers=1, progress=False)
    assert run(study, out, workers=1, progress=False, stale="rerun").y.tolist() == [0, 2] and _executions() == 4
    monkeypatch.delenv("OMP_NUM_THREADS")
    with pytest.raises(StaleTrialsError, match=r"\(OMP_NUM_THREADS 2 → unset\)"):
        run(study, out, workers=1, progress=False)


def test_a_change_in_an_ocpkit_module_the_trial_runs_is_refused_naming_it(trial_folder, tmp_path, monkeypatch):
    """ocpkit's own files cannot be edited here: their hash is altered as an edit would alter it."""
    from ocpkit.runs import provenance
    from ocpkit.sim import metrics

    _module(
        trial_folder,
        "stale_trial_d",
        """
        import os, pathlib, time
        def trial(x):
            from ocpkit.sim.metrics import itae
            pathlib.Path(os.environ["STALE_TEST_LOG"], f"{x}-{time.time_ns()}").touch()
            return {"y": x}
    """,
    )
    import stale_trial_d

    study = Study("s", stale_trial_d.trial, grid(x=range(2)))
    run(study, tmp_path / "out", workers=1, progress=False)
    read = provenance._read

    def edited(path):
        digest, refs = read(path)
        return (digest[::-1], refs) if Path(path) == Path(metrics.__file__) else (digest, refs)

    monkeypatch.setattr(provenance, "_read", edited)
    # (other ocpkit modules may be named too where someone edits them meanwhile)
    with pytest.raises(StaleTrialsError, match=r"\(changed [^;)]*\bocpkit\.sim\.metrics\b"):
        run(study, tmp_path / "out", workers=1, progress=False)


def test_a_closed_loop_trials_manifest_covers_the_solvers_and_problems_it_may_run():
    """The solver and problem modules are imported by computed name (``import_module(f"ocpkit.solvers.{name}")``):
    all of them count; modules the trial never imports (the CLI, the store, other studies) do not."""
    from ocpkit.runs import provenance
    from ocpkit.studies import closed_loop

    code = provenance.manifest(closed_loop.trial)["code"]
    for name in (
        "ocpkit.studies.closed_loop",
        "ocpkit.solvers.qp",
        "ocpkit.solvers.nlp",
        "ocpkit.solvers.mppi",
        "ocpkit.problems.nlink",
        "ocpkit.problems.baxter",
        "ocpkit.sim.simulate",
        "ocpkit.sim.metrics",
        "ocpkit",
        "ocpkit.studies",
    ):
        assert name in code, name
    for name in (
        "ocpkit.cli",
        "ocpkit.runs.store",
        "ocpkit.runs.study",
        "ocpkit.studies.knots",
        "ocpkit.studies.report",
        "ocpkit.benchmarks.faults",
    ):
        assert name not in code, name
    assert not any(name.startswith(("numpy", "casadi", "scipy")) for name in code)  # versions, not files
    assert all(len(digest) == 16 for digest in code.values())


def test_the_public_api_counts_only_the_names_a_trial_uses(trial_folder):
    """``ocpkit/__init__.py`` imports its public names on first use (``__getattr__``): a trial that imports only
    ``ocpkit.model`` does not run the solvers; one that uses ``ocpkit.LinearMPC``, or imports it (inside the trial
    function: it runs when the trial does), runs ``ocpkit.solvers.qp`` and not the other controllers."""
    from ocpkit.runs import provenance

    _module(
        trial_folder,
        "stale_model_only_f",
        """
        import ocpkit.model
        def trial(x):
            return {"y": x}
    """,
    )
    _module(
        trial_folder,
        "stale_attribute_f",
        """
        import ocpkit
        def trial(x):
            return {"y": ocpkit.LinearMPC.__name__}
    """,
    )
    _module(
        trial_folder,
        "stale_from_f",
        """
        def trial(x):
            from ocpkit import LinearMPC
            return {"y": LinearMPC.__name__}
    """,
    )
    import stale_attribute_f
    import stale_from_f
    import stale_model_only_f

    code = provenance.manifest(stale_model_only_f.trial)["code"]
    assert "ocpkit.model" in code and not any(name.startswith("ocpkit.solvers") for name in code), sorted(code)
    for module in (stale_attribute_f, stale_from_f):
        code = provenance.manifest(module.trial)["code"]
        assert "ocpkit.solvers.qp" in code, sorted(code)
        assert not {"ocpkit.solvers.nlp", "ocpkit.solvers.empc", "ocpkit.sim.simulate"} & set(code), sorted(code)


def test_hashing_is_cached_per_process(tmp_path, monkeypatch):
    """Each file is read and parsed once per process; again only when its stat changes."""
    from ocpkit.runs import provenance
    from ocpkit.studies import closed_loop

    monkeypatch.setattr(provenance, "_FILES", {})  # the baseline: every file read and parsed (~0.2 s)
    t0 = time.perf_counter()
    first = provenance.manifest(closed_loop.trial)
    uncached = time.perf_counter() - t0

    def parse(source):
        raise AssertionError("a file was parsed again although it did not change")

    monkeypatch.setattr(provenance, "_imports", parse)
    t0 = time.perf_counter()
    for _ in range(5):
        assert provenance.manifest(closed_loop.trial) == first
    # Stats and look-ups only (~15 ms on a busy 2-core machine): a fraction of the baseline, however busy it is.
    assert (time.perf_counter() - t0) / 5 < uncached / 3
    monkeypatch.undo()
    helper = tmp_path / "cached_helper.py"
    helper.write_text("import json\n")
    assert provenance._read(str(helper))[1] == (("import", "json"),)
    _touch_later(helper, "import csv\n")
    assert provenance._read(str(helper))[1] == (("import", "csv"),)  # changed: read again


def test_a_change_in_the_users_problem_file_is_refused_naming_it(cartpole_dir):
    """`ocpkit study … --problem ./cartpole.py:CartPole`: the trial runs the user's file, named in its parameters."""
    from ocpkit.studies import closed_loop

    params = {"problem": "./cartpole.py:CartPole", "seed": 0, "knots": 2, "horizon": 10, "duration": 0.05}
    study = Study("cp", closed_loop.trial, [params])
    first = run(study, "out", workers=1, progress=False)
    assert (first.status == "ok").all(), first.error.tolist()
    source = cartpole_dir / "cartpole.py"
    _touch_later(source, source.read_text().replace("M, m, l, g = 1.0 * error", "M, m, l, g = 2.0 * error"))
    with pytest.raises(StaleTrialsError, match=r"1 of the 1 stored trials of study 'cp'.*\(changed \./cartpole\.py\b"):
        run(study, "out", workers=1, progress=False)
    kept = run(study, "out", workers=1, progress=False, stale="reuse")
    assert kept.actual_cost.tolist() == first.actual_cost.tolist()
    again = run(study, "out", workers=1, progress=False, stale="rerun")
    assert (again.status == "ok").all() and again.actual_cost.tolist() != first.actual_cost.tolist()


def test_trials_stored_by_0_1_0_are_refused_saying_what_is_known(trial_folder, tmp_path):
    """Trials from before manifests were recorded: the version change is named, the code's is said to be unknown."""
    from ocpkit.runs.store import Store
    from ocpkit.runs.study import package_version

    _module(trial_folder, "stale_helper_e", "FACTOR = 2\n")
    _module(trial_folder, "stale_trial_e", _TRIAL.format(helper="stale_helper_e"))
    import stale_trial_e

    with Store(tmp_path / "out") as store:
        store.write("s", {"x": 1}, {"y": 2}, version="0.1.0", code="0123456789abcdef")
    study = Study("s", stale_trial_e.trial, grid(x=range(2)))
    now = re.escape(package_version())
    with pytest.raises(
        StaleTrialsError,
        match=rf"1 of the 1 stored trials .*\(ocpkit 0\.1\.0 → {now}; code recorded "
        r"before ocpkit 0\.2\.0 .* unknown\)",
    ):
        run(study, tmp_path / "out", workers=1, progress=False)
    assert run(study, tmp_path / "out", workers=1, progress=False, stale="reuse").y.tolist() == [0, 2]
    assert _executions() == 1

"""Compiling the learned filters' kernels ahead (``togglecf.run.warmup``): what ``make run`` starts beside
its grids must fill numba's cache with what its tasks call, and must never stop the job."""
import logging
import subprocess
import sys
import tempfile

from togglecf.run import warmup


def test_each_family_runs_and_a_bad_name_is_one_usage_line():
    for family in warmup.FAMILIES:
        warmup.compile_kernels(family)  # in this process: compiled or loaded from the cache
    res = subprocess.run([sys.executable, "-m", "togglecf.run.warmup", "kalman"], capture_output=True, text=True)
    assert res.returncode == 2
    assert res.stderr.strip() == "usage: python -m togglecf.run.warmup toggling|vqf"


def test_batch_and_in_loop_share_one_compiled_step():
    # the batch loop (gain searches) and the in-loop models (scoring) pass the coefficients by value
    # (PredictionDrivenFilter.step_params), so each step has one signature in 9D and 6D, and the kernels
    # compiled ahead are the ones both call (arrays in one, tuples in the other compiled each step twice)
    code = ("from togglecf.run import warmup\n"
            "from togglecf.filters.toggling import TogglingFilter\n"
            "from togglecf.filters.vqf_toggling import VQFTogglingFilter\n"
            "for f in warmup.FAMILIES: warmup.compile_kernels(f)\n"
            "print(len(TogglingFilter.step.signatures), len(VQFTogglingFilter.step.signatures))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["1", "1"]


def test_a_failed_warm_up_is_a_warning_not_an_error(caplog):
    err = tempfile.TemporaryFile()  # as start_compiling gives each process
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.exit('no pretrained model')"], stderr=err)
    with caplog.at_level(logging.WARNING, logger="togglecf.run.warmup"):
        warmup.Compiling({"toggling": (proc, err)}).wait()
    assert "compiling the toggling kernels ahead failed (no pretrained model): the tasks compile them" in caplog.text

"""One logging set-up: progress on stderr through the ``togglecf`` logger, results on stdout."""
import logging

from togglecf.core.log import setup_logging
from togglecf.data.broad import DatasetIndex
from togglecf.run.config import load_config
from togglecf.run.sweep import evaluate_trials
from togglecf.run.train import run_training


def test_setup_is_idempotent_and_follows_the_current_stderr(capsys):
    logger = setup_logging()
    setup_logging()
    assert sum(h.get_name() == "togglecf-stderr" for h in logger.handlers) == 1
    logging.getLogger("togglecf.run.train").info("progress line")
    out, err = capsys.readouterr()  # capsys replaced sys.stderr after the handler was made
    assert "progress line" in err and out == ""


def test_training_progress_goes_to_stderr_and_the_cv_table_to_stdout(mini_index, tmp_path, capsys):
    setup_logging()
    cfg = load_config()
    cfg["run"]["cv_folds"] = 2
    cfg["classifier"].update(n_estimators=4, max_depth=3)
    cfg["regressor"].update(n_estimators=2, max_depth=3)
    cfg["gains"]["learn"] = False
    run_training(cfg, data_dir=mini_index.root, trials="02,24", out=tmp_path / "m", cv=True, verbose=True)
    out, err = capsys.readouterr()
    assert "togglecf train: 2 trials" in err and "wrote" in err  # progress
    assert "balacc" in out and "togglecf train:" not in out  # the result table


def test_evaluate_results_are_returned_not_printed(mini_index, mini_names, capsys):
    res = evaluate_trials(DatasetIndex.from_dir(mini_index.root), [mini_names[0]], "madgwick", [{}], jobs=1)
    assert res[0][mini_names[0]].errors["total"] > 0
    assert capsys.readouterr().out == ""

"""The jobs: scoring filters on trials, sweeps (evaluate, tune), training, the held-out study and
the pruning sweep."""
from togglecf.run.config import load_config
from togglecf.run.scoring import TrialResult, parse_grid, run_filter, score_trial, score_trials
from togglecf.run.study import load_study_config, run_study
from togglecf.run.sweep import ResultStore, evaluate_trials, grid_search, run_sweep
from togglecf.run.train import run_training

__all__ = ["load_config", "TrialResult", "parse_grid", "run_filter", "score_trial", "score_trials",
           "load_study_config", "run_study", "ResultStore", "evaluate_trials", "grid_search", "run_sweep",
           "run_training"]

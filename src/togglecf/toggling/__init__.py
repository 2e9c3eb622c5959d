"""The trained toggling filter: its models compiled into the loop (``inloop``), the gains learned
on training trials (``gains``), and loading a trained filter from a model directory (``load``).
The toggling *step* itself is ML-free and lives in ``togglecf.filters.toggling``."""
from togglecf.toggling.gains import GAINS_FILE, GainSearch, learn_gains, load_gains, save_gains
from togglecf.toggling.inloop import ModelTogglingFilter
from togglecf.toggling.load import load_compiled_models, load_toggling_filter, model_dir_digest

__all__ = ["GAINS_FILE", "GainSearch", "learn_gains", "load_gains", "save_gains", "ModelTogglingFilter",
           "load_compiled_models", "load_toggling_filter", "model_dir_digest"]

"""Put the pretrained learned VQF of `make run` (reports/pretrained: learned_vqf.npz, MODEL_CARD.md) into
the package (src/togglecf/toggling/pretrained/), only when its model card's no-harm check passed on every
dataset left out; says whether the package's copy was already the same (same bytes: `make run`
reproduces the shipped model exactly).

    python pipelines/ship_pretrained.py [--from reports/pretrained]
"""
import argparse
import shutil
import sys
from pathlib import Path

from togglecf.core.io import file_sha256
from togglecf.learn.portable import load_portable
from togglecf.toggling.pretrained import MODEL_CARD_FILE, PRETRAINED_DIR, PRETRAINED_FILE


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--from", dest="src", type=Path, default=Path("reports/pretrained"),
                   help="the directory step 5 of pipelines/main.py wrote (default: %(default)s)")
    args = p.parse_args(argv)
    model, card = args.src / PRETRAINED_FILE.name, args.src / MODEL_CARD_FILE.name
    for f in (model, card):
        if not f.is_file():
            print(f"{f}: not found; run `python pipelines/main.py` (step 5) first", file=sys.stderr)
            return 1
    check = load_portable(model).metadata.get("no_harm") or {}
    failed = [f"{ds}: learned VQF {c['learned_vqf']:.2f}° vs VQF {c['vqf']:.2f}° ({100 * (c['ratio'] - 1):+.1f} %)"
              for ds, c in check.items() if not c["passed"]]
    if not check or failed:
        print(f"{model}: not shipped: " + ("no leave-one-dataset-out check in its metadata" if not check
                                           else "worse than VQF + 2 % on " + "; ".join(failed)), file=sys.stderr)
        return 1
    same = PRETRAINED_FILE.is_file() and file_sha256(PRETRAINED_FILE) == file_sha256(model)
    PRETRAINED_DIR.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(model, PRETRAINED_FILE)
    shutil.copyfile(card, MODEL_CARD_FILE)
    print(f"{PRETRAINED_FILE}: " + ("unchanged (the same bytes)" if same else f"updated from {model}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())

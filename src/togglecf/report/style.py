"""One colour and line style per filter, used by every figure (``report.plots``, ``report.study_report``).

``FILTER_STYLE`` maps a filter's name (the CLI name, plus ``"vqf"`` for the reference package and
``"truth"`` for the optical ground truth) to its matplotlib line properties; ``style(name)`` looks a
name up with a fallback, so any name gets the same look in every picture:

* a known name: its entry;
* a variant ``<known>_<suffix>`` (the study's ``toggling_6d``, ``madgwick_6d``, ablations such as
  ``toggling_only``): the base filter's colour, dash-dotted;
* anything else: a colour from ``FALLBACK_COLORS`` chosen by a hash of the name (stable across
  runs and processes, unlike Python's ``hash``), dotted.

Colours are Tableau 10 (colour-blind-safe enough for lines with distinct styles), the reference
filters in neutral tones: VQF grey, the truth black.
"""
from __future__ import annotations

import zlib

__all__ = ["FILTER_STYLE", "FALLBACK_COLORS", "style", "color"]

#: name -> matplotlib line properties (``ax.plot(..., **style(name))``)
FILTER_STYLE: dict[str, dict] = {
    "toggling": {"color": "#1f77b4", "linestyle": "-", "linewidth": 1.2},    # blue: the filter of this project
    "vqf": {"color": "#7f7f7f", "linestyle": "-", "linewidth": 1.0},         # grey: the reference package (C++)
    "vqf_core": {"color": "#17becf", "linestyle": "--", "linewidth": 1.0},   # cyan, dashed: our VQF core
    "vqf_toggling": {"color": "#c51b7d", "linestyle": "-", "linewidth": 1.4},  # magenta: the VQF core, learned
    "learned_vqf": {"color": "#c51b7d", "linestyle": "-", "linewidth": 1.4},   # the same, pretrained
    "madgwick": {"color": "#d62728", "linestyle": "-", "linewidth": 1.0},    # red
    "cf": {"color": "#2ca02c", "linestyle": "-", "linewidth": 1.0},          # green: the fixed-gain CF
    "mahony": {"color": "#9467bd", "linestyle": "-", "linewidth": 1.0},      # purple
    "aqua": {"color": "#ff7f0e", "linestyle": "-", "linewidth": 1.0},        # orange
    "ekf": {"color": "#8c564b", "linestyle": "-", "linewidth": 1.0},         # brown
    "gyro": {"color": "#bcbd22", "linestyle": ":", "linewidth": 1.0},        # olive, dotted: a bound
    "accmag": {"color": "#e377c2", "linestyle": ":", "linewidth": 1.0},      # pink, dotted: a bound
    "truth": {"color": "#000000", "linestyle": "-", "linewidth": 1.6},       # black, thicker
}

#: colours for names not in ``FILTER_STYLE`` (none of them used there)
FALLBACK_COLORS = ("#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd", "#e6550d", "#31a354")


def style(name: str) -> dict:
    """Line properties of ``name`` (a fresh dict: ``color``, ``linestyle``, ``linewidth``); see the module doc."""
    if name in FILTER_STYLE:
        return dict(FILTER_STYLE[name])
    base = next((b for b in sorted(FILTER_STYLE, key=len, reverse=True) if name.startswith(b + "_")), None)
    if base is not None and base != "truth":
        return {**FILTER_STYLE[base], "linestyle": "-."}
    k = zlib.crc32(name.encode()) % len(FALLBACK_COLORS)
    return {"color": FALLBACK_COLORS[k], "linestyle": ":", "linewidth": 1.0}


def color(name: str) -> str:
    """The colour of ``name`` (bars, markers)."""
    return style(name)["color"]

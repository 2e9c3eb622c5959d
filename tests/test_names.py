"""One name per quantity in Python and C: the struct members of the C twins (``tcf_vqf.h``,
``tcf_vqf_toggling.h``, ``tcf_filter.h``, read from the headers with a small parser) are the field
names of the Python filters' state and coefficient records, for the VQF core, the learned VQF and the
toggling CF. Where the two sides differ on purpose, the difference is written down below with its
reason; every other difference fails, and so does a written-down exception that no longer applies.

Member order is not compared: the C layouts are fixed (``TCF_*_STATE_BYTES``, flags and low-pass
heads grouped), the Python records are ordered by the kernels' needs.

Rules that apply to every filter (not listed per name):

* a low-pass bank ``B`` of the Python state, a record ``(n, ready, s)`` with ``s`` ``(channels, 2)``,
  is ``B_head`` (``tcf_vqf_lp_head_t``: ``n``, ``ready``) and ``B`` (``float [channels][2]``, the
  ``s``) in C: the layout groups the heads before the channels;
* a Python state vector written as flat names ``x_x, x_y, x_z`` (the toggling CF) is ``x[3]`` in C.
"""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from togglecf.embedded import cvqf
from togglecf.filters.base import COMMON_STATE_FIELDS
from togglecf.filters.toggling import TogglingCoefficients, TogglingFilter
from togglecf.filters.vqf_core import CoreModulation, LowPass, VQFCoreCoefficients, VQFCoreFilter, VQFCoreSettings
from togglecf.filters.vqf_toggling import VQFTogglingCoefficients, VQFTogglingFilter

EMBEDDED = Path(cvqf.__file__).parent

# ------------------------------------------------------------------------------------ exceptions
# name -> reason, one line each. C_ONLY: members with no Python field of that name; PY_ONLY: fields
# with no C member; RENAMED: Python name -> (C name, reason) for a different quantity of the same role.

CORE_STATE_C_ONLY = {
    "c": "the coefficients (VQFCoreCoefficients) live in the C state so one tcf_vqf_t is all a sensor needs; "
         "Python passes them as the kernel's params (compared below as tcf_vqf_coef_t)",
    "k_mag_last": "the heading gain of the last sample, kept for tcf_vqf_harness; Python returns it per sample "
                  "as the diagnostic k_mag",
}
CORE_COEF_NESTED = {
    "modulation": "C has CoreModulation's fields in line in tcf_vqf_coef_t (the layout is fixed); "
                  "tcf_vqf_mod_t is the separate per-sample record, compared with CoreModulation",
}
LOWPASS_RENAMED = {
    "decay": ("one_minus_decay", "C keeps 1 - a2 (near 0, exact in float32; the C arithmetic is fixed), "
                                 "Python keeps a2 itself"),
}
SETTINGS_C_ONLY = {
    "fs": "the rate: VQFCoreFilter's constructor argument fs, not a setting",
    "use_mag": "9D or 6D: VQFCoreFilter's constructor argument use_mag, not a setting",
}
VQFT_STATE_C_ONLY = {
    "core": "the core's tcf_vqf_t (state and coefficients) nested; Python's record starts with the core's "
            "fields in line (compared above)",
    "feat": "the models' feature window and held prediction; Python keeps them outside the filter, "
            "with the models (toggling.inloop)",
}
VQFT_STATE_PY_ONLY = {
    "mag_backoff": "the back-off factor 1 + e of the last sample (a record of the step); C applies it "
                   "and keeps no copy",
}
#: coefficients held in the C state struct (derived from the rate at init; the others are macros)
VQFT_COEF_IN_STATE = {"modulation_gain": "derived from fs at tcf_vqft_init, so it cannot be a macro",
                      "field_change_gain": "derived from fs at tcf_vqft_init, so it cannot be a macro"}
#: coefficients that are compile-time macros of the generated tcf_config.h: name -> macro
VQFT_COEF_MACROS_RENAMED = {
    "layout": ("TCF_N_CLASSES", "the prediction row's layout is fixed at export: TCF_N_CLASSES and "
                                "tcf_prediction.h"),
}
CF_STATE_C_ONLY = {
    "c": "the per-sample coefficients (TogglingCoefficients, compared below) live in the C state; "
         "Python passes them as the kernel's params",
    "feat": "the models' feature window and held prediction; Python keeps them with the models "
            "(toggling.inloop)",
}
#: C state members that hold the last sample's diagnostics: must be names of TogglingFilter.diagnostic_names
CF_STATE_DIAGNOSTICS = ("alpha_acc", "alpha_mag", "p_static")
CF_COEF_C_ONLY = {
    "ts": "the nominal sampling time 1/fs [s], tcf_filter_update's dt; Python keeps it as the filter's Ts",
}
CF_COEF_MACROS_RENAMED = {
    "layout": ("TCF_N_CLASSES", "the prediction row's layout is fixed at export: TCF_N_CLASSES and "
                                "tcf_prediction.h"),
}


# ------------------------------------------------------------------------------------ C parser

_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
_STRUCT = re.compile(r"typedef\s+struct\s*\w*\s*\{(?P<body>[^{}]*)\}\s*(?P<name>\w+)\s*;")
_DECLARATOR = re.compile(r"\**\s*(?P<name>\w+)\s*(?P<dims>(?:\[[^\]]*\]\s*)*)$")


def c_structs(text: str) -> dict[str, dict[str, tuple]]:
    """The ``typedef struct ... { ... } name_t;`` blocks of C source ``text``: ``{name_t: {member:
    (type, dims)}}`` in declaration order, ``dims`` the array sizes as written (``("3", "2")``;
    ``()`` for a scalar). One declaration may name several members (``float a, b[3];``)."""
    out = {}
    for m in _STRUCT.finditer(_COMMENT.sub(" ", text)):
        members = {}
        for decl in m["body"].split(";"):
            decl = " ".join(decl.split())
            if not decl:
                continue
            kind = re.match(r"(?:const\s+)?(\w+)\s+", decl)
            if kind is None:
                raise ValueError(f"{m['name']}: cannot read the declaration {decl!r}")
            for part in decl[kind.end():].split(","):
                d = _DECLARATOR.match(part.strip())
                if d is None:
                    raise ValueError(f"{m['name']}: cannot read the declarator {part!r} of {decl!r}")
                members[d["name"]] = (kind[1], tuple(re.findall(r"\[\s*([^\]]*?)\s*\]", d["dims"])))
        out[m["name"]] = members
    return out


def name_drift(what: str, python, c, *, c_only=(), py_only=(), renamed=None) -> list[str]:
    """The differences between the Python names ``python`` and the C names ``c`` that are not
    written down: names on one side only (outside ``c_only``/``py_only``), ``renamed`` pairs
    (Python -> (C, reason)) not found as such, and written-down exceptions that no longer apply
    (the name is on both sides, or missing from its own side). Empty when the lists agree."""
    renamed = renamed or {}
    py, cc = set(python), set(c)
    py_r = (py - set(renamed)) | {renamed[n][0] for n in py & set(renamed)}
    out = [f"{what}: {n!r} only in Python" for n in sorted(py_r - cc - set(py_only))]
    out += [f"{what}: {n!r} only in C" for n in sorted(cc - py_r - set(c_only))]
    out += [f"{what}: exception {n!r} (C only) is stale" for n in sorted(set(c_only) - (cc - py_r))]
    out += [f"{what}: exception {n!r} (Python only) is stale" for n in sorted(set(py_only) - (py_r - cc))]
    out += [f"{what}: renaming {p!r} -> {cn!r} is stale" for p, (cn, _) in sorted(renamed.items())
            if p not in py or cn not in cc]
    return out


@pytest.fixture(scope="module")
def structs():
    out = {}
    for h in ("tcf_vqf.h", "tcf_vqf_toggling.h", "tcf_filter.h"):
        out.update(c_structs((EMBEDDED / h).read_text()))
    return out


def _c_source(*names) -> str:
    return _COMMENT.sub(" ", "\n".join((EMBEDDED / n).read_text() for n in names))


# ------------------------------------------------------------------------------------ Python side

def _banks(dtype) -> list[str]:
    """The state fields of ``dtype`` that are low-pass banks (sub-records ``n, ready, s``)."""
    return [n for n in dtype.names if dtype[n].names == ("n", "ready", "s")]


def _state_names_as_c(dtype, names=None) -> list[str]:
    """The state field names of ``dtype`` (or ``names`` of it) under the bank rule (module docstring)."""
    banks = set(_banks(dtype))
    out = []
    for n in dtype.names if names is None else names:
        out += [f"{n}_head", n] if n in banks else [n]
    return out


def _flat_groups(names) -> list[str]:
    """Flat state names ``x_x, x_y, x_z`` -> ``x`` (the toggling CF's state, module docstring)."""
    out = []
    for n in names:
        g = re.sub(r"_[xyz]$", "", n)
        if g not in out:
            out.append(g)
    return out


# ------------------------------------------------------------------------------------ the VQF core

def test_vqf_core_state(structs):
    dtype = VQFCoreFilter.state_dtype
    assert [n for n, _ in COMMON_STATE_FIELDS] == list(dtype.names[:2])
    c = structs["tcf_vqf_t"]
    assert not name_drift("tcf_vqf_t / VQFCoreFilter state", _state_names_as_c(dtype), c,
                          c_only=CORE_STATE_C_ONLY)
    # and the shapes: a C array [a][b] is the Python field's shape (a bank's channels: its s)
    for n in dtype.names:
        sub = dtype[n]["s"] if n in _banks(dtype) else dtype[n]
        assert tuple(int(d) for d in c[n][1]) == sub.shape, n


def test_vqf_core_bank_head(structs):
    dtype = VQFCoreFilter.state_dtype
    for b in _banks(dtype):
        assert structs["tcf_vqf_t"][f"{b}_head"][0] == "tcf_vqf_lp_head_t", b
    head = [n for n in dtype[_banks(dtype)[0]].names if n != "s"]
    assert not name_drift("tcf_vqf_lp_head_t / bank record", head, structs["tcf_vqf_lp_head_t"])


def test_vqf_core_coefficients(structs):
    python = []
    for f in VQFCoreCoefficients._fields:
        python += list(CoreModulation._fields) if f in CORE_COEF_NESTED else [f]
    assert set(CORE_COEF_NESTED) <= set(VQFCoreCoefficients._fields)
    assert not name_drift("tcf_vqf_coef_t / VQFCoreCoefficients", python, structs["tcf_vqf_coef_t"])
    assert not name_drift("tcf_vqf_mod_t / CoreModulation", CoreModulation._fields, structs["tcf_vqf_mod_t"])
    assert not name_drift("tcf_vqf_lp_coef_t / LowPass", LowPass._fields, structs["tcf_vqf_lp_coef_t"],
                          renamed=LOWPASS_RENAMED)


def test_vqf_core_settings(structs):
    python = [f.name for f in dataclasses.fields(VQFCoreSettings)]
    assert not name_drift("tcf_vqf_params_t / VQFCoreSettings", python, structs["tcf_vqf_params_t"],
                          c_only=SETTINGS_C_ONLY)


# ------------------------------------------------------------------------------------ the learned VQF

def test_learned_vqf_state(structs):
    dtype, core = VQFTogglingFilter.state_dtype, VQFCoreFilter.state_dtype
    assert dtype.names[:len(core.names)] == core.names  # the core's fields first, in line
    own = [n for n in dtype.names if n not in core.names]
    c = [n for n in structs["tcf_vqft_t"] if n not in VQFT_COEF_IN_STATE]
    assert not name_drift("tcf_vqft_t / VQFTogglingFilter state", _state_names_as_c(dtype, own), c,
                          c_only=VQFT_STATE_C_ONLY, py_only=VQFT_STATE_PY_ONLY)
    assert structs["tcf_vqft_t"]["core"][0] == "tcf_vqf_t" and structs["tcf_vqft_t"]["mod"][0] == "tcf_vqf_mod_t"


def test_learned_vqf_coefficients(structs):
    """The core's coefficients are tcf_vqf_coef_t (core.c); of the learned ones, those derived from
    the rate are state members, the rest macros TCF_VQFT_<NAME> (per-state arrays: _INIT)."""
    own = [f for f in VQFTogglingCoefficients._fields if f not in VQFCoreCoefficients._fields]
    assert set(VQFT_COEF_IN_STATE) <= set(own) and set(VQFT_COEF_IN_STATE) <= set(structs["tcf_vqft_t"])
    macros = set(re.findall(r"\bTCF_\w+", _c_source("tcf_vqf_toggling.c")))
    missing = []
    for f in own:
        if f in VQFT_COEF_IN_STATE:
            continue
        want = VQFT_COEF_MACROS_RENAMED[f][0] if f in VQFT_COEF_MACROS_RENAMED else f"TCF_VQFT_{f.upper()}"
        if not {want, f"{want}_INIT"} & macros:
            missing.append(f"{f} -> {want}")
    assert not missing, f"learned VQF coefficients without their C macro: {missing}"


# ------------------------------------------------------------------------------------ the toggling CF

def test_toggling_cf_state(structs):
    python = [n for n, _ in COMMON_STATE_FIELDS] + _flat_groups(TogglingFilter.state_names)
    c = [n for n in structs["tcf_filter_t"] if n not in CF_STATE_DIAGNOSTICS]
    assert not name_drift("tcf_filter_t / TogglingFilter state", python, c, c_only=CF_STATE_C_ONLY)
    assert set(CF_STATE_DIAGNOSTICS) <= set(TogglingFilter.diagnostic_names)
    assert set(CF_STATE_DIAGNOSTICS) <= set(structs["tcf_filter_t"])


def test_toggling_cf_coefficients(structs):
    """Those derived from the rate are tcf_filter_coeffs_t members; the rest are macros TCF_<NAME>."""
    c = structs["tcf_filter_coeffs_t"]
    macros = set(re.findall(r"\bTCF_\w+", _c_source("tcf_filter.c")))
    as_macro = {f: (CF_COEF_MACROS_RENAMED[f][0] if f in CF_COEF_MACROS_RENAMED else f"TCF_{f.upper()}")
                for f in TogglingCoefficients._fields if f not in c}
    missing = [f"{f} -> {m}" for f, m in as_macro.items() if m not in macros]
    assert not missing, f"toggling CF coefficients neither a member nor their C macro: {missing}"
    assert not name_drift("tcf_filter_coeffs_t / TogglingCoefficients",
                          [f for f in TogglingCoefficients._fields if f not in as_macro], c, c_only=CF_COEF_C_ONLY)


# ------------------------------------------------------------------------------------ the checker itself

PLANTED = """
/* a made-up header */
typedef struct demo_lp { float k, beta; } demo_lp_t;   // a comment { with a brace }
typedef struct demo {
  demo_lp_t c;            /* coefficients */
  float quat[4];          /* orientation */
  uint32_t rest;          /* drifted from rest_detected */
  float bank[9][2], other;
  const float *ptr;
} demo_t;
"""


def test_parser_reads_members_types_and_dims():
    s = c_structs(PLANTED)
    assert list(s) == ["demo_lp_t", "demo_t"]
    assert s["demo_lp_t"] == {"k": ("float", ()), "beta": ("float", ())}
    assert s["demo_t"] == {"c": ("demo_lp_t", ()), "quat": ("float", ("4",)), "rest": ("uint32_t", ()),
                           "bank": ("float", ("9", "2")), "other": ("float", ()), "ptr": ("float", ())}


def test_checker_fails_on_planted_drift():
    s = c_structs(PLANTED)
    python = ["quat", "rest_detected", "bank", "other", "ptr"]
    drift = name_drift("demo", python, s["demo_t"], c_only={"c": "coefficients"})
    assert drift == ["demo: 'rest_detected' only in Python", "demo: 'rest' only in C"]
    assert not name_drift("demo", [*python[:1], "rest", *python[2:]], s["demo_t"], c_only={"c": "coefficients"})
    # a different quantity passes only when written down, and the written-down pair must exist
    assert name_drift("lp", ["k", "decay"], s["demo_lp_t"]) == ["lp: 'decay' only in Python", "lp: 'beta' only in C"]
    assert not name_drift("lp", ["k", "decay"], s["demo_lp_t"], renamed={"decay": ("beta", "1 - decay")})
    assert name_drift("lp", ["k", "decay"], s["demo_lp_t"], renamed={"decay": ("one_minus_decay", "")}) == [
        "lp: 'one_minus_decay' only in Python", "lp: 'beta' only in C",
        "lp: renaming 'decay' -> 'one_minus_decay' is stale"]
    # an exception that no longer applies fails too
    fixed = [*python[:1], "rest", *python[2:]]
    assert name_drift("demo", [*fixed, "c"], s["demo_t"], c_only={"c": "coefficients"}) == [
        "demo: exception 'c' (C only) is stale"]
    assert name_drift("demo", ["quat"], {"quat": 0}, py_only={"gone": "x"}) == [
        "demo: exception 'gone' (Python only) is stale"]


def test_checker_sees_a_drift_in_the_real_header(structs):
    """The real tcf_vqf.h with one member renamed back to its old C name fails the core's check."""
    text = (EMBEDDED / "tcf_vqf.h").read_text().replace("uint32_t rest_detected;", "uint32_t rest;")
    planted = c_structs(text)["tcf_vqf_t"]
    drift = name_drift("tcf_vqf_t", _state_names_as_c(VQFCoreFilter.state_dtype), planted, c_only=CORE_STATE_C_ONLY)
    assert drift == ["tcf_vqf_t: 'rest_detected' only in Python", "tcf_vqf_t: 'rest' only in C"]

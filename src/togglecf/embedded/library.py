"""An exported C filter as an Arduino / PlatformIO library: the folder layout both
tools read, written by ``cvqf_toggling.export_c_vqf_toggling`` into ``<out_dir>/arduino/<name>/``::

    <name>/
      library.properties          Arduino Library Manager metadata (includes= the API header)
      library.json                PlatformIO metadata (frameworks arduino, any platform, no -ffast-math)
      README.md                   rate at init, units, frames, memory, TCF_MAX_FS
      src/                        the firmware sources and headers of the export (no host harness)
      examples/<example>/<example>.ino   a sketch: reads an IMU at IMU_RATE_HZ, calls the filter

The sketch's filter calls sit in one block between ``SKETCH_C_BEGIN`` and ``SKETCH_C_END`` written
in the common subset of C and C++ (``sketch_c_calls`` returns it), so a test can compile exactly
those calls as C99 for a target without an Arduino tool chain.
"""
from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

from togglecf import __version__
from togglecf.core.io import atomic_write_text

__all__ = ["LibrarySpec", "SKETCH_C_BEGIN", "SKETCH_C_END", "write_library", "sketch_c_calls"]

SKETCH_C_BEGIN = "/* ---- the filter calls (plain C: tests compile this block as C99) ---- */"
SKETCH_C_END = "/* ---- end of the filter calls ---- */"


@dataclass(frozen=True)
class LibrarySpec:
    """What the library says about its filter: ``name`` (library and folder, e.g.
    ``TogglecfLearnedVQF``), ``example`` (sketch name), ``sentence`` (one line), ``api_header``,
    ``files`` (the export's firmware sources and headers copied into ``src/``), ``state_type``
    and the C calls of the sketch: ``init`` (``{state}``, ``{rate}``: an int return code),
    ``update`` (``{state}``, ``gyr``, ``acc``, ``mag``, ``dt_s``), ``quat`` (``{state}``, ``q``);
    ``readme``: the README's text after the title."""

    name: str
    example: str
    sentence: str
    api_header: str
    files: tuple
    state_type: str
    init: str
    update: str
    quat: str
    readme: str


def _properties(spec: LibrarySpec) -> str:
    """``library.properties`` (Arduino 1.5 library format)."""
    return "\n".join([f"name={spec.name}", f"version={__version__}", "author=togglecf", "maintainer=togglecf",
                      f"sentence={spec.sentence}",
                      "paragraph=C99, float32, no heap: one state record per sensor. The sampling rate is set at "
                      "init, the per-sample time step is an argument of the update.",
                      "category=Sensors", "url=https://pypi.org/project/togglecf/", "architectures=*",
                      f"includes={spec.api_header}", ""])


def _library_json(spec: LibrarySpec) -> str:
    """``library.json`` (PlatformIO library manifest)."""
    return json.dumps({"name": spec.name, "version": __version__, "description": spec.sentence,
                       "keywords": ["imu", "orientation", "ahrs", "sensor-fusion", "vqf"],
                       "authors": [{"name": "togglecf"}], "frameworks": ["arduino"], "platforms": "*",
                       "headers": spec.api_header, "build": {"flags": ["-fno-fast-math"]}}, indent=2) + "\n"


def sketch_c_calls(spec: LibrarySpec) -> str:
    """The sketch's filter calls (between ``SKETCH_C_BEGIN`` and ``SKETCH_C_END``): one static
    state, ``filter_begin(rate_hz)`` (the init's return code) and ``filter_step(gyr, acc, mag,
    dt_s, q)``; valid C99 and C++."""
    st = "filt"
    return f"""{SKETCH_C_BEGIN}
static {spec.state_type} {st};  /* all filter state (static: no heap, not on the stack) */

/* the rate [Hz] of your IMU's samples; returns TCF_OK (0) or an error code (tcf_features.h) */
static int filter_begin(float rate_hz) {{
  return {spec.init.format(state="&" + st, rate="rate_hz")};
}}

/* one sample: gyr [rad/s], acc [m/s^2], mag [uT] or NULL (6D), sensor frame; dt_s [s] since the
   previous sample; q: the orientation [w, x, y, z], sensor -> ENU */
static void filter_step(const float gyr[3], const float acc[3], const float mag[3], float dt_s, float q[4]) {{
  {spec.update.format(state="&" + st)};
  {spec.quat.format(state="&" + st)};
}}
{SKETCH_C_END}"""


def _sketch(spec: LibrarySpec, rate_hz: float) -> str:
    """``examples/<example>/<example>.ino``: a placeholder IMU read (a sensor at rest, paced by
    ``micros()``) to replace with the board's driver, the filter calls, the quaternion on Serial."""
    return f"""/* {spec.example}.ino: the {spec.sentence[0].lower() + spec.sentence[1:].rstrip('.')}
 * on an Arduino board. Replace readImu() with your IMU driver and set IMU_RATE_HZ to its output
 * data rate; the filter takes the rate at init and the actual time step of every sample.
 * Units: gyr rad/s, acc m/s^2, mag uT, in the sensor frame; output quaternion [w, x, y, z],
 * sensor -> earth (ENU: x east, y north, z up). */
#include <Arduino.h>
#include <{spec.api_header}>

#define IMU_RATE_HZ {rate_hz:g}f  /* your IMU's output data rate [Hz], at most TCF_MAX_FS */
#define HAVE_MAG 1             /* 0: no magnetometer (mag = NULL: 6D, no heading) */

/* One new sample in SI units (return 1), or none yet (return 0). Placeholder: a sensor at rest,
   level, paced by micros(); replace it with your driver (data-ready interrupt or FIFO). */
static int readImu(float gyr[3], float acc[3], float mag[3]) {{
  static unsigned long next_us = 0;
  if ((long)(micros() - next_us) < 0) return 0;
  next_us += (unsigned long)(1e6f / IMU_RATE_HZ);
  gyr[0] = 0.0f; gyr[1] = 0.0f; gyr[2] = 0.0f;
  acc[0] = 0.0f; acc[1] = 0.0f; acc[2] = 9.81f;
  mag[0] = 0.0f; mag[1] = 20.0f; mag[2] = -40.0f;
  return 1;
}}

{sketch_c_calls(spec)}

static unsigned long last_us;

void setup() {{
  Serial.begin(115200);
  int rc = filter_begin(IMU_RATE_HZ);
  if (rc != TCF_OK) {{
    Serial.print("filter init failed: ");
    Serial.println(rc);
    for (;;) {{
    }}
  }}
  last_us = micros() - (unsigned long)(1e6f / IMU_RATE_HZ);
}}

void loop() {{
  float gyr[3], acc[3], mag[3], q[4];
  if (!readImu(gyr, acc, mag)) return;
  unsigned long now = micros();
  float dt_s = (float)(now - last_us) * 1e-6f;  /* the actual step: jitter and lost samples handled */
  last_us = now;
  filter_step(gyr, acc, HAVE_MAG ? mag : NULL, dt_s, q);
  Serial.print(q[0], 6); Serial.print(' ');
  Serial.print(q[1], 6); Serial.print(' ');
  Serial.print(q[2], 6); Serial.print(' ');
  Serial.println(q[3], 6);
}}
"""


def write_library(out_dir: Path, spec: LibrarySpec, rate_hz: float) -> Path:
    """Write the library of the export in ``out_dir`` (whose files ``spec.files`` it copies into
    ``src/``) to ``out_dir/arduino/<spec.name>/``, the sketch set to ``rate_hz`` [Hz]; returns
    the library folder (rewritten from scratch)."""
    lib = Path(out_dir) / "arduino" / spec.name
    shutil.rmtree(lib, ignore_errors=True)
    (lib / "src").mkdir(parents=True)
    for name in spec.files:
        shutil.copyfile(Path(out_dir) / name, lib / "src" / name)
    atomic_write_text(lib / "library.properties", _properties(spec))
    atomic_write_text(lib / "library.json", _library_json(spec))
    atomic_write_text(lib / "README.md", f"# {spec.name}\n\n{spec.readme}")
    (lib / "examples" / spec.example).mkdir(parents=True)
    atomic_write_text(lib / "examples" / spec.example / f"{spec.example}.ino", _sketch(spec, rate_hz))
    return lib

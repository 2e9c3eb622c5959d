"""Live orientation from a serial IMU stream (or a file / stdin), sample by sample.

Line protocol, one sample a line, comma-separated, ``\\n`` or ``\\r\\n`` terminated::

    t,gx,gy,gz,ax,ay,az,mx,my,mz        (9D; 6D: t,gx,gy,gz,ax,ay,az)

``t`` in seconds, milliseconds or microseconds (``time_unit``); gyr/acc/mag in the units given
(``units``), converted at the boundary to rad/s, m/s² and µT. Each valid sample is run through
the filter with the real Δt from consecutive timestamps (the first sample gets ``1/fs``);
quaternion ``[w, x, y, z]`` (sensor -> ENU) and ZYX Euler angles [deg] are printed at ``rate``
Hz of stream time. Bad input never crashes the stream: garbage bytes, undecodable or overlong
lines, non-numeric or non-finite fields and wrong field counts are skipped; timestamp gaps
(dropped samples) are counted and bridged with the real Δt; timestamps going backwards or
jumping more than ``max_gap`` s (a device reset) restart the time base (that sample skipped);
serial errors close the port and retry. Every problem is counted, the first few of each kind
are reported to stderr, and the counts are summarised at the end.

Units are checked on the first ``unit_check_s`` seconds of samples (held back, then filtered): a field
whose values another unit explains (``togglecf.core.units.unit_mismatch``, the trial loader's check: gyro
in °/s, acc in g or mg, mag in gauss, mT or nT) stops the stream with one line (``UnitError``) naming
the field, the statistic seen and the ``--units`` that fixes it; vigorous motion is never refused.

The core (``StreamProcessor.feed``/``run``) takes any iterable of ``bytes`` chunks, so it is the
same code for a serial port (``serial_chunks``), a file or a pipe (``file_chunks``).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from togglecf.core import quaternion as quat
from togglecf.core.extras import deferred
from togglecf.core.units import TIME_UNITS, parse_units, unit_mismatch, units_option

serial = deferred("serial", extra="stream", what="togglecf stream --port")

#: markers a chunk source yields after opening a port (CONNECTED) and after reopening it
#: (RECONNECT): the partial line in the buffer is dropped and the input is resynchronised by
#: discarding everything up to the next newline (a port is usually opened mid-line)
CONNECTED = object()
RECONNECT = object()

class UnitError(ValueError):
    """A stream field read in the wrong unit (``StreamConfig.unit_check_s``); the message is one line."""


PROBLEMS = ("garbage", "non_numeric", "non_finite", "wrong_field_count", "overlong_line", "dropped_samples",
            "time_reset", "reconnects", "partial_line_dropped")


@dataclass
class StreamConfig:
    fs: float = 285.714  # nominal rate [Hz]: dt of the first sample, gap detection
    time_unit: str = "s"
    units: str | None = None  # e.g. "gyr=dps,acc=g,mag=uT"
    use_mag: bool = True
    rate: float = 10.0  # output rate [Hz of stream time]; 0 = every sample
    gap_factor: float = 1.5  # Δt > gap_factor/fs counts round(Δt·fs) − 1 dropped samples
    max_gap: float = 1.0  # Δt > max_gap [s] or Δt <= 0: the time base restarts
    max_line: int = 512  # bytes; longer "lines" are garbage
    precision: int = 6  # decimals printed
    report_first: int = 5  # problems of each kind reported individually to stderr
    record: bool = False  # keep every (t, dt, q) in memory (tests, notebooks)
    unit_check_s: float = 2.0  # samples held back to check the units [s at fs]; 0: no check

    def __post_init__(self):
        if self.time_unit not in TIME_UNITS:
            raise ValueError(f"time unit must be one of {', '.join(TIME_UNITS)}, got {self.time_unit!r}")
        if not (self.fs > 0 and self.rate >= 0 and self.max_gap > 0 and self.unit_check_s >= 0):
            raise ValueError("fs and max_gap must be > 0, rate and unit_check_s >= 0")
        self.factors = parse_units(self.units)
        self.n_fields = 10 if self.use_mag else 7


@dataclass
class StreamProcessor:
    """Parses byte chunks into samples and runs ``filt`` (any togglecf filter) on them."""

    filt: object
    config: StreamConfig = field(default_factory=StreamConfig)
    out: object = None  # text stream for the orientation lines (default sys.stdout)
    err: object = None  # text stream for problem reports (default sys.stderr)

    def __post_init__(self):
        self.out = self.out if self.out is not None else sys.stdout
        self.err = self.err if self.err is not None else sys.stderr
        self.counts = dict.fromkeys(PROBLEMS, 0)
        self.n_lines = 0
        self.n_samples = 0
        self._buf = bytearray()
        self._sync = False
        self._last_t = None
        self._next_print = -math.inf
        self.records = {"t": [], "dt": [], "quat": []}
        self._gf, self._af, self._mf = self.config.factors
        self._tf = TIME_UNITS[self.config.time_unit]
        self._Ts = 1.0 / self.config.fs
        #: samples held back until the units are checked: (t, dt, gyr, acc, mag), None where the time base
        #: restarted; None once checked
        self._held = [] if self.config.unit_check_s > 0 else None
        self._n_check = max(1, round(self.config.unit_check_s * self.config.fs))
        self._n_held = 0

    # -- problems ------------------------------------------------------------------------------
    def _problem(self, kind, detail="", n=1):
        self.counts[kind] += n
        if self.counts[kind] - n < self.config.report_first:
            more = " (further ones counted silently)" if self.counts[kind] >= self.config.report_first else ""
            print(f"stream: {kind.replace('_', ' ')}: {detail}{more}", file=self.err)

    # -- input ---------------------------------------------------------------------------------
    def feed(self, chunk):
        """Bytes (any split, partial lines kept until their newline), or ``CONNECTED`` /
        ``RECONNECT``."""
        if chunk is CONNECTED or chunk is RECONNECT:
            if chunk is RECONNECT:
                self.counts["reconnects"] += 1
            if self._buf:
                self._problem("partial_line_dropped", f"{bytes(self._buf[:40])!r} before a reconnect")
                self._buf.clear()
            self._sync = True
            return
        if self._sync:
            i = chunk.find(b"\n")
            if i < 0:
                self._buf += chunk  # still looking for the first newline
                if len(self._buf) > self.config.max_line:
                    self._problem("overlong_line", f"{len(self._buf)} bytes without a newline")
                    self._buf.clear()
                return
            head = bytes(self._buf) + chunk[:i]
            self._buf.clear()
            self._sync = False
            if head.strip():
                self._problem("partial_line_dropped", f"{head[:40]!r} (resynchronising after a connect)")
            chunk = chunk[i + 1:]
        self._buf += chunk
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                break
            line = bytes(self._buf[:i])
            del self._buf[:i + 1]
            self.feed_line(line)
        if len(self._buf) > self.config.max_line:
            self._problem("overlong_line", f"{len(self._buf)} bytes without a newline: {bytes(self._buf[:40])!r}")
            self._buf.clear()

    def finish(self):
        """End of input: a trailing line without newline is processed, the samples held for the unit check
        are checked and filtered; summary to stderr."""
        if self._buf:
            line = bytes(self._buf)
            self._buf.clear()
            self.feed_line(line)
        if self._held:
            self._check_units()
        print(self.summary(), file=self.err)

    def run(self, chunks):
        """Process a whole iterable of chunks, then ``finish``. Returns ``self.counts``."""
        try:
            for chunk in chunks:
                self.feed(chunk)
        except KeyboardInterrupt:
            pass
        self.finish()
        return self.counts

    def summary(self) -> str:
        bad = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in self.counts.items() if v)
        return f"stream: {self.n_lines} lines, {self.n_samples} samples filtered; problems: {bad or 'none'}"

    def feed_line(self, raw: bytes):
        self.n_lines += 1
        raw = raw.strip()
        if not raw or raw.startswith(b"#"):
            return
        if len(raw) > self.config.max_line:
            self._problem("overlong_line", f"{len(raw)} bytes")
            return
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self._problem("garbage", repr(raw[:60]))
            return
        parts = text.split(",")
        if parts[0].strip().lower() in ("t", "time", "timestamp"):
            return  # a header line
        if len(parts) != self.config.n_fields:
            self._problem("wrong_field_count", f"{len(parts)} fields, expected {self.config.n_fields}: {text[:60]!r}")
            return
        try:
            v = [float(p) for p in parts]
        except ValueError:
            self._problem("non_numeric", repr(text[:60]))
            return
        if not all(map(math.isfinite, v)):
            self._problem("non_finite", repr(text[:60]))
            return
        self._sample(v)

    # -- filtering -----------------------------------------------------------------------------
    def _sample(self, v):
        t = v[0] * self._tf
        if self._last_t is None:
            dt = self._Ts
        else:
            dt = t - self._last_t
            if not (0.0 < dt <= self.config.max_gap):
                self._problem("time_reset", f"Δt = {dt:.6g} s at t = {t:.6g} s: time base restarted, sample skipped")
                self._last_t = t
                if self._held is not None:
                    self._held.append(None)  # the print times restart here when the held samples are filtered
                else:
                    self._next_print = -math.inf
                return
            if dt > self.config.gap_factor * self._Ts:
                n = max(1, int(round(dt / self._Ts)) - 1)
                self._problem("dropped_samples", f"{n} missing before t = {t:.6g} s (Δt = {dt * 1e3:.2f} ms)", n)
        self._last_t = t
        gf, af, mf = self._gf, self._af, self._mf
        gyr = np.array((v[1] * gf, v[2] * gf, v[3] * gf))
        acc = np.array((v[4] * af, v[5] * af, v[6] * af))
        mag = np.array((v[7] * mf, v[8] * mf, v[9] * mf)) if self.config.use_mag else None
        if self._held is not None:
            self._held.append((t, dt, gyr, acc, mag))
            self._n_held += 1
            if self._n_held >= self._n_check:
                self._check_units()
            return
        self._filter(t, dt, gyr, acc, mag)

    def _check_units(self):
        """The held samples' units (``UnitError`` on a field another unit explains), then those samples
        filtered in order."""
        held, self._held = self._held, None
        samples = [h for h in held if h is not None]
        fields = {"gyr": 2, "acc": 3, "mag": 4} if self.config.use_mag else {"gyr": 2, "acc": 3}
        for (quantity, k), factor in zip(fields.items(), self.config.factors):
            wrong = unit_mismatch(quantity, np.array([h[k] for h in samples]), factor)
            if wrong is not None:
                raise UnitError(f"field {quantity!r} over the first {len(samples)} samples: {wrong.describe()}; "
                                f"rerun with --units {units_option(self.config.units, quantity, wrong.unit)} "
                                "(--unit-check 0 skips this check)")
        for sample in held:
            if sample is None:
                self._next_print = -math.inf
            else:
                self._filter(*sample)

    def _filter(self, t, dt, gyr, acc, mag):
        q = self.filt.update(gyr, acc, mag, dt=dt)
        self.n_samples += 1
        if self.config.record:
            self.records["t"].append(t)
            self.records["dt"].append(dt)
            self.records["quat"].append(q)
        if t >= self._next_print:
            self._emit(t, q)
            period = 1.0 / self.config.rate if self.config.rate > 0 else 0.0
            # a fixed grid of print times (no drift from the sample spacing); after a pause, restart
            nxt = self._next_print + period
            self._next_print = nxt if t < nxt else t + period

    def _emit(self, t, q):
        rpy = np.degrees(quat.to_euler_zyx(q))
        p = self.config.precision
        vals = ",".join(f"{x:.{p}f}" for x in (*q, *rpy))
        print(f"{t:.6f},{vals}", file=self.out, flush=True)


OUTPUT_HEADER = "t,qw,qx,qy,qz,roll_deg,pitch_deg,yaw_deg"


# -- chunk sources --------------------------------------------------------------------------------
def file_chunks(f, size: int = 4096):
    """Byte chunks of a binary file-like object (``read1`` when present: a pipe's data as it
    arrives); text streams are read through their ``buffer``."""
    f = getattr(f, "buffer", f)
    read = getattr(f, "read1", f.read)
    while True:
        chunk = read(size)
        if not chunk:
            return
        yield chunk


def serial_chunks(port: str, baud: int = 115200, retry_s: float = 1.0, max_reconnects: int | None = None,
                  idle_timeout: float | None = None, serial_factory=None, err=None, sleep=time.sleep):
    """Byte chunks read from a serial port; on a serial/OS error the port is closed, reported,
    and reopened every ``retry_s`` s (``CONNECTED`` is yielded after opening, ``RECONNECT`` after
    each reopening) — up to
    ``max_reconnects`` times (None: forever). Ends after ``idle_timeout`` s without data (None:
    never). ``serial_factory(port, baud)`` opens the port (default ``serial.Serial``)."""
    err = err if err is not None else sys.stderr
    if serial_factory is None:
        def serial_factory(port, baud):
            return serial.Serial(port, baud, timeout=0.05)
    reconnects = 0
    ser = None
    last_data = time.monotonic()
    while True:
        try:
            if ser is None:
                ser = serial_factory(port, baud)
                yield RECONNECT if reconnects else CONNECTED
            chunk = ser.read(max(1, ser.in_waiting))
            if chunk:
                last_data = time.monotonic()
                yield chunk
            elif idle_timeout is not None and time.monotonic() - last_data > idle_timeout:
                ser.close()
                return
        except (serial.SerialException, OSError) as exc:
            if ser is not None:
                try:
                    ser.close()
                except Exception:  # noqa: BLE001 - a broken port may fail to close too
                    pass
                ser = None
            if max_reconnects is not None and reconnects >= max_reconnects:
                print(f"stream: serial error ({exc}); giving up after {reconnects} reconnects", file=err)
                return
            reconnects += 1
            print(f"stream: serial error ({exc}); reconnect {reconnects} in {retry_s:g} s", file=err)
            sleep(retry_s)
            last_data = time.monotonic()



"""``togglecf.live.stream``: a corrupted 286 Hz line stream through a pseudo-terminal read with
pyserial gives exactly the batch filter's orientation on the valid samples."""
import io
import os
import threading
import time
import tty

import numpy as np
import pytest

from togglecf import simulate as sim
from togglecf.filters import make_filter
from togglecf.cli.main import main
from togglecf.live.stream import (RECONNECT, StreamConfig, StreamProcessor, UnitError, file_chunks, parse_units,
                                  serial_chunks)

serial = pytest.importorskip("serial")

FS = 285.714


def _signals(n, seed=3):
    q = sim.random_smooth_trajectory(FS, n / FS + 1.0, seed=seed)[:n]
    return sim.imu_from_orientation(q, FS, gyro_noise=0.01, acc_noise=0.05, mag_noise=0.5, seed=seed)


def _corrupted_stream(trial, seed=0):
    """Lines in ms / dps / g / µT with corrupted and dropped lines mixed in. Returns the bytes,
    the indices of the samples that are valid, the parsed (exact) values of those, and the
    expected problem counts."""
    rng = np.random.default_rng(seed)
    n = trial.n_samples
    t_ms = np.arange(n) * (1000.0 / FS)
    gyr = np.degrees(trial.gyr)
    acc = trial.acc / 9.80665
    lines, valid, vals = [], [], []
    counts = dict(garbage=0, non_numeric=0, non_finite=0, wrong_field_count=0, dropped_lines=0)
    kinds = ["garbage", "garbage_prefix", "truncated", "nan", "extra", "missing", "word", "drop"]
    for i in range(n):
        row = [t_ms[i], *gyr[i], *acc[i], *trial.mag[i]]
        line = ",".join(repr(float(x)) for x in row)
        kind = kinds[rng.integers(len(kinds))] if (i > 0 and rng.random() < 0.04) else None
        if kind == "garbage":  # a burst of non-ASCII bytes, its own line
            lines.append(bytes(rng.integers(0x80, 0x100, rng.integers(3, 30)).astype(np.uint8)))
            counts["garbage"] += 1
            lines.append(line.encode())
        elif kind == "garbage_prefix":  # noise glued to the start: the sample is lost
            lines.append(b"\xff\xfe\x00" + line.encode())
            counts["garbage"] += 1
            continue
        elif kind == "truncated":  # cut in its first 60 %: fewer fields
            lines.append(line[: rng.integers(1, int(0.6 * len(line)))].rstrip(",").encode() + b",")
            continue  # counted by the processor as wrong count or ... see below
        elif kind in ("nan", "word"):  # one field replaced by a non-finite or a non-numeric token
            parts = line.split(",")
            parts[rng.integers(1, 10)] = "nan" if kind == "nan" else "abc"
            lines.append(",".join(parts).encode())
            counts["non_finite" if kind == "nan" else "non_numeric"] += 1
            continue
        elif kind == "extra":
            lines.append((line + ",1.0").encode())
            counts["wrong_field_count"] += 1
            continue
        elif kind == "missing":
            lines.append(line.rsplit(",", 1)[0].encode())
            counts["wrong_field_count"] += 1
            continue
        elif kind == "drop":
            counts["dropped_lines"] += 1
            continue
        else:
            lines.append(line.encode())
        valid.append(i)
        vals.append([float(s) for s in line.split(",")])
    eol = [b"\r\n" if rng.random() < 0.5 else b"\n" for _ in lines]
    data = b"".join(l + e for l, e in zip(lines, eol))
    return data, np.array(valid), np.array(vals), counts


def _expected(vals, use_mag=True):
    """The batch filter on the valid samples with the stream's per-sample Δt."""
    t = vals[:, 0] * 1e-3
    dt = np.diff(t, prepend=np.nan)
    dt[0] = 1.0 / FS
    f = make_filter("madgwick", FS, use_mag=use_mag)
    gyr = vals[:, 1:4] * (np.pi / 180.0)
    acc = vals[:, 4:7] * 9.80665
    out = f.update_batch(gyr, acc, vals[:, 7:10] if use_mag else None, dt=dt)
    return t, dt, out.quat


def _config(**kw):
    return StreamConfig(fs=FS, time_unit="ms", units="gyr=dps,acc=g,mag=uT", record=True, **kw)


def test_pty_serial_stream_equals_batch_on_valid_samples():
    trial = _signals(11_000)
    data, valid, vals, counts = _corrupted_stream(trial)
    assert len(data.splitlines()) >= 10_000

    master, slave = os.openpty()
    tty.setraw(slave)
    rng = np.random.default_rng(1)

    def writer():  # random chunk sizes: lines split across reads
        pos = 0
        while pos < len(data):
            k = int(rng.integers(1, 700))
            pos += os.write(master, data[pos:pos + k])

    th = threading.Thread(target=writer, daemon=True)

    def open_port(port, baud):  # pyserial flushes the input on open: start writing after it
        ser = serial.Serial(port, baud, timeout=0.05)
        th.start()
        return ser

    out, err = io.StringIO(), io.StringIO()
    proc = StreamProcessor(make_filter("madgwick", FS), _config(rate=10.0), out=out, err=err)
    t0 = time.perf_counter()
    try:
        proc.run(serial_chunks(os.ttyname(slave), 115200, idle_timeout=2.0, err=err, serial_factory=open_port))
        th.join(5)
    finally:
        os.close(master)
        os.close(slave)
    elapsed = time.perf_counter() - t0

    # the first line after opening the port is discarded (resynchronisation: ports open mid-line)
    assert valid[0] == 0 and proc.counts["partial_line_dropped"] == 1
    t, dt, q_batch = _expected(vals[1:])
    rec = proc.records
    assert proc.n_samples == len(valid) - 1, err.getvalue()[-2000:]
    np.testing.assert_array_equal(np.array(rec["t"]), t)
    np.testing.assert_array_equal(np.array(rec["dt"]), dt)
    np.testing.assert_allclose(np.array(rec["quat"]), q_batch, rtol=0, atol=1e-9)
    # problems: counted, never crashed
    c = proc.counts
    assert c["garbage"] == counts["garbage"]
    assert c["non_finite"] == counts["non_finite"]
    assert c["non_numeric"] == counts["non_numeric"]
    assert c["wrong_field_count"] >= counts["wrong_field_count"]  # + truncated lines
    assert c["time_reset"] == 0 and c["reconnects"] == 0
    n_missing = trial.n_samples - len(valid)
    assert c["dropped_samples"] == n_missing  # every lost line shows up as a timestamp gap
    assert "problems:" in err.getvalue() and "dropped samples" in err.getvalue()
    # printed output: ~10 lines per second of stream time, the last one printed = that sample's state
    printed = np.loadtxt(io.StringIO(out.getvalue()), delimiter=",")
    assert abs(len(printed) - 10 * t[-1]) <= 2
    k = np.searchsorted(t, printed[-1, 0] - 5e-7)
    np.testing.assert_allclose(printed[-1, 1:5], q_batch[k], atol=2e-6)
    assert elapsed < 30


def test_file_and_reconnect_paths():
    trial = _signals(1500, seed=5)
    data, valid, vals, _ = _corrupted_stream(trial, seed=2)
    t, dt, q_batch = _expected(vals)

    # whole file through file_chunks (pipe/stdin path)
    proc = StreamProcessor(make_filter("madgwick", FS), _config(rate=0), out=io.StringIO(), err=io.StringIO())
    proc.run(file_chunks(io.BytesIO(data), size=97))
    np.testing.assert_allclose(np.array(proc.records["quat"]), q_batch, atol=1e-9)
    assert len(proc.out.getvalue().splitlines()) == len(valid)  # rate 0: every sample printed

    # a port that fails mid-line twice, then delivers the rest after reconnecting
    cut1, cut2 = len(data) // 3 + 5, 2 * len(data) // 3 + 7
    pieces = [data[:cut1], data[cut1:cut2], data[cut2:]]

    class FlakyPort:
        opened = 0

        def __init__(self, port, baud):
            self.piece = pieces[FlakyPort.opened]
            FlakyPort.opened += 1
            self.pos = 0

        @property
        def in_waiting(self):
            return min(300, len(self.piece) - self.pos)

        def read(self, k):
            if self.pos >= len(self.piece):
                if FlakyPort.opened < len(pieces):
                    raise serial.SerialException("device disconnected")
                return b""
            chunk = self.piece[self.pos:self.pos + k]
            self.pos += len(chunk)
            return chunk

        def close(self):
            pass

    err = io.StringIO()
    proc = StreamProcessor(make_filter("madgwick", FS), _config(rate=0), out=io.StringIO(), err=err)
    chunks = serial_chunks("/dev/fake", serial_factory=FlakyPort, idle_timeout=0.2, err=err, sleep=lambda s: None)
    proc.run(chunks)
    assert FlakyPort.opened == 3
    assert "reconnect 2" in err.getvalue() and proc.counts["reconnects"] == 2
    assert 2 <= proc.counts["partial_line_dropped"] <= 5  # the first line, and the cut lines' ends
    # the first line and the two lines cut by the disconnects are lost; the rest equals the batch run
    assert len(valid) - 3 <= proc.n_samples <= len(valid) - 1
    got_t = np.array(proc.records["t"])
    keep = np.isin(t, got_t)
    _, _, q2 = _expected(vals[keep])
    np.testing.assert_allclose(np.array(proc.records["quat"]), q2, atol=1e-9)


def test_time_reset_and_units():
    assert parse_units("gyr=dps,acc=g") == (np.pi / 180, 9.80665, 1.0)
    with pytest.raises(ValueError):
        parse_units("gyr=rpm")
    err = io.StringIO()
    proc = StreamProcessor(make_filter("madgwick", FS, use_mag=False), StreamConfig(fs=FS, use_mag=False, record=True),
                           out=io.StringIO(), err=err)
    lines = b"t,gx,gy,gz,ax,ay,az\n0.0,0,0,0,0,0,9.8\n0.0035,0,0,0,0,0,9.8\n0.001,0,0,0,0,0,9.8\n" \
            b"0.0045,0,0,0,0,0,9.8\n" + b"x" * 2000 + b"\n0.008,0,0,0,0,0,9.8"
    proc.run([RECONNECT, lines])  # resync drops the header line
    assert proc.counts["reconnects"] == 1
    assert proc.counts["time_reset"] == 1  # 0.001 after 0.0035: restarted, skipped
    assert proc.counts["overlong_line"] == 1
    assert proc.n_samples == 4  # the unterminated last line is processed at the end
    np.testing.assert_allclose(proc.records["dt"], [1 / FS, 0.0035, 0.0035, 0.0035])


def _cli(argv):
    import argparse

    from togglecf.cli.stream import add_stream_parser

    p = argparse.ArgumentParser(prog="togglecf")
    add_stream_parser(p.add_subparsers(dest="command"))
    args = p.parse_args(argv)
    return args.func(args)


def test_cli_stream_from_file_and_stdin(tmp_path, capsys, monkeypatch):
    trial = _signals(600, seed=7)
    data, valid, vals, _ = _corrupted_stream(trial, seed=4)
    path = tmp_path / "imu.csv"
    path.write_bytes(b"t,gx,gy,gz,ax,ay,az,mx,my,mz\n" + data)
    argv = ["stream", "--input", str(path), "--units", "gyr=dps,acc=g,mag=uT", "--time-unit", "ms",
            "--rate", "0", "--precision", "12", "--filter", "madgwick", "--fs", str(FS)]
    assert _cli(argv) == 0
    cap = capsys.readouterr()
    lines = cap.out.splitlines()
    assert lines[0] == "t,qw,qx,qy,qz,roll_deg,pitch_deg,yaw_deg"
    printed = np.loadtxt(io.StringIO(cap.out), delimiter=",", skiprows=1)
    _, _, q_batch = _expected(vals)
    assert printed.shape == (len(valid), 8)
    np.testing.assert_allclose(printed[:, 1:5], q_batch, atol=1e-11)
    assert "problems:" in cap.err

    # stdin ("-"): same output
    monkeypatch.setattr("sys.stdin", io.TextIOWrapper(io.BytesIO(path.read_bytes())))
    assert _cli(argv[:1] + ["--input", "-"] + argv[3:]) == 0
    assert capsys.readouterr().out == cap.out

    with pytest.raises(ValueError, match="unknown unit"):
        _cli(["stream", "--input", str(path), "--units", "gyr=rpm", "--fs", "100"])
    # no silent rate: a 100-Hz file run at a guessed 285.714 Hz scales every time constant by 2.86
    with pytest.raises(SystemExit):
        _cli(["stream", "--input", str(path)])
    assert "--fs" in capsys.readouterr().err


def _lines(trial, gyr_scale=1.0, acc_scale=1.0, mag_scale=1.0):
    """The trial as stream lines in seconds, each field multiplied by its scale (a sensor in other units)."""
    rows = np.column_stack([np.arange(trial.n_samples) / FS, trial.gyr * gyr_scale, trial.acc * acc_scale,
                            trial.mag * mag_scale])
    return b"".join(",".join(repr(float(x)) for x in r).encode() + b"\n" for r in rows)


@pytest.mark.parametrize("scales,units,field,fix", [
    ({"gyr_scale": 180 / np.pi}, None, "gyr", "gyr=dps"),
    ({"acc_scale": 1 / 9.80665}, None, "acc", "acc=g"),
    ({"acc_scale": 1000 / 9.80665}, "gyr=rad/s", "acc", "gyr=rad/s,acc=mg"),
    ({"mag_scale": 0.01}, "gyr=rad/s,mag=uT", "mag", "gyr=rad/s,mag=gauss"),
    ({"mag_scale": 0.001}, None, "mag", "mag=mT"),
    ({"mag_scale": 1000.0}, None, "mag", "mag=nT"),
], ids=["gyr_dps", "acc_g", "acc_mg", "mag_gauss", "mag_mT", "mag_nT"])
def test_a_field_in_another_unit_stops_the_stream_before_any_output(scales, units, field, fix):
    """The first seconds of samples are checked with the trial loader's check (``core.units.unit_mismatch``):
    one line naming the field, the statistic seen and the ``--units`` that fixes it; nothing filtered before.
    With that ``--units`` the same lines run."""
    trial = _signals(1500, seed=11)
    data = _lines(trial, **scales)
    out = io.StringIO()
    proc = StreamProcessor(make_filter("madgwick", FS), StreamConfig(fs=FS, units=units), out=out, err=io.StringIO())
    with pytest.raises(UnitError) as exc:
        proc.run([data])
    msg = str(exc.value)
    assert "\n" not in msg and f"field '{field}' over the first 571 samples" in msg  # 2 s at 285.714 Hz
    assert f"rerun with --units {fix} " in msg
    assert out.getvalue() == "" and proc.n_samples == 0
    proc = StreamProcessor(make_filter("madgwick", FS), StreamConfig(fs=FS, units=fix, record=True), out=io.StringIO(),
                           err=io.StringIO())
    proc.run([data])
    assert proc.n_samples == trial.n_samples
    batch = make_filter("madgwick", FS).update_batch(trial.gyr, trial.acc, trial.mag).quat
    np.testing.assert_allclose(proc.records["quat"], batch, atol=1e-9)  # the held samples filtered as the rest


def test_vigorous_motion_a_short_stream_and_no_check_are_accepted():
    trial = _signals(1500, seed=12)
    # a phone in a running hand: median |acc| 20-24 m/s²; no other unit explains it
    running = _lines(trial, acc_scale=2.3)
    proc = StreamProcessor(make_filter("madgwick", FS), StreamConfig(fs=FS, rate=0), out=io.StringIO(), err=io.StringIO())
    proc.run([running])
    assert proc.n_samples == trial.n_samples and len(proc.out.getvalue().splitlines()) == trial.n_samples
    # shorter than the check: checked at the end, then filtered
    short = _lines(trial, acc_scale=1 / 9.80665).splitlines(keepends=True)[:100]
    with pytest.raises(UnitError, match="field 'acc' over the first 100 samples: median"):
        StreamProcessor(make_filter("madgwick", FS), StreamConfig(fs=FS), out=io.StringIO(),
                        err=io.StringIO()).run([b"".join(short)])
    proc = StreamProcessor(make_filter("madgwick", FS), StreamConfig(fs=FS, unit_check_s=0), out=io.StringIO(),
                           err=io.StringIO())
    proc.run([b"".join(short)])  # --unit-check 0: no check
    assert proc.n_samples == 100


def test_cli_stream_refuses_a_unit_in_one_line(tmp_path, capsys):
    path = tmp_path / "imu.csv"
    path.write_bytes(_lines(_signals(1500, seed=13), acc_scale=1 / 9.80665))
    assert main(["stream", "--input", str(path), "--fs", str(FS), "--filter", "madgwick"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"togglecf stream: error: field 'acc' over the first 571 samples: median |acc| = 1: looks like g, "
                   f"expected m/s²; rerun with --units gyr=rad/s,acc=g,mag=uT (--unit-check 0 skips this check)"]

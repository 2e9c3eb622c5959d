"""``togglecf download``: fetch BROAD's repository archive and unpack only the data.

The archive (``BROAD_ARCHIVE_URL``) is streamed to a temporary file beside the target;
only the trial files (``data_hdf5/*.hdf5`` and/or ``data_mat/*.mat``) and ``trials.json``
are unpacked, each to a temporary name, checked (zip CRC, then read back with
``load_trial``) and only then renamed into place. On any failure nothing half-written is
left behind.
"""
from __future__ import annotations

import json
import logging
import shutil
import tempfile
import urllib.request
import zipfile
from pathlib import Path, PurePosixPath

from togglecf.core.progress import progress
from togglecf.data.broad import BROAD_URL, DataError, load_trial

__all__ = ["download_broad", "BROAD_ARCHIVE_URL"]

log = logging.getLogger(__name__)

BROAD_ARCHIVE_URL = f"{BROAD_URL}/archive/refs/heads/main.zip"
_FOLDERS = {"hdf5": ("data_hdf5",), "mat": ("data_mat",), "both": ("data_hdf5", "data_mat")}


def download_broad(dest, url: str = BROAD_ARCHIVE_URL, fmt: str = "hdf5", timeout: float = 60.0) -> Path:
    """Download BROAD into ``dest`` and return it. ``fmt``: ``hdf5``, ``mat`` or ``both``."""
    if fmt not in _FOLDERS:
        raise ValueError(f"format must be one of {sorted(_FOLDERS)}, got {fmt!r}")
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    log.info(f"downloading BROAD from {url} into {dest}")
    fd, archive = tempfile.mkstemp(prefix=".broad-archive.", suffix=".zip.part", dir=dest)
    archive = Path(archive)
    try:
        with open(fd, "wb") as out:
            _fetch(url, out, timeout)
        try:
            zf = zipfile.ZipFile(archive)
        except zipfile.BadZipFile as exc:
            raise DataError(url, None, f"downloaded file is not a zip archive: {exc}") from None
        with zf:
            written = _extract(zf, dest, _FOLDERS[fmt])
    finally:
        archive.unlink(missing_ok=True)
    log.info(f"unpacked and verified {written} trial files and trials.json into {dest}")
    return dest


def _fetch(url, out, timeout):
    try:
        with urllib.request.urlopen(url, timeout=timeout) as resp:
            total = int(resp.headers.get("Content-Length") or 0) or None
            with progress(total=total, unit="B", unit_scale=True, desc="download", iterable=None) as bar:
                while chunk := resp.read(1 << 20):
                    out.write(chunk)
                    bar.update(len(chunk))
    except OSError as exc:  # URLError, HTTPError, timeouts are all OSErrors
        raise DataError(url, None, f"download failed: {exc}. Get BROAD by hand from {BROAD_URL} "
                                   f"(folders data_hdf5/ or data_mat/) and pass --data DIR") from None


def _extract(zf: zipfile.ZipFile, dest: Path, folders) -> int:
    members = {}
    index_member = None
    for info in zf.infolist():
        p = PurePosixPath(info.filename)
        if info.is_dir() or len(p.parts) < 2 or p.parent.name not in _FOLDERS["both"]:
            continue
        if p.name == "trials.json":
            index_member = index_member or info
        elif p.parent.name in folders and p.suffix in (".hdf5", ".mat"):
            members[p.name] = info
    if index_member is None or not members:
        raise DataError(zf.filename, None, f"archive holds no BROAD data ({'/'.join(folders)}/ and trials.json)")
    count = 0
    for name, info in progress(sorted(members.items()) + [("trials.json", index_member)], desc="unpack", unit="file"):
        target = dest / name
        tmp = dest / f".{Path(name).stem}.part{Path(name).suffix}"  # real suffix: load_trial picks the reader
        try:
            with zf.open(info) as src, open(tmp, "wb") as out:
                shutil.copyfileobj(src, out, 1 << 20)  # zipfile checks the CRC at the end of the stream
            if name == "trials.json":
                try:
                    json.loads(tmp.read_text())["trials"]
                except (ValueError, KeyError, TypeError) as exc:
                    raise DataError(name, None, f"downloaded trials.json is not BROAD's index: {exc}") from None
            else:
                try:
                    load_trial(tmp)
                except DataError as exc:
                    raise DataError(name, None, f"downloaded trial fails verification: {exc.problem}") from None
                count += 1
            tmp.replace(target)
        except zipfile.BadZipFile as exc:
            raise DataError(zf.filename, name, f"archive member is corrupt: {exc}") from None
        finally:
            tmp.unlink(missing_ok=True)
    return count


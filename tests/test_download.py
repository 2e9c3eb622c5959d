"""`togglecf download` against a local HTTP server on 127.0.0.1 (no test reaches the internet)."""
import functools
import http.server
import io
import json
import threading
import zipfile

import pytest

from togglecf.data.broad import DataError, DatasetIndex
from togglecf.data.download import download_broad
from test_data import make_broad_dir


@pytest.fixture
def server(tmp_path):
    root = tmp_path / "www"
    root.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(root))
    handler.log_message = lambda *a, **k: None
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield root, f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()
    httpd.server_close()


def build_archive(src_dir, dest_zip, corrupt_member=None, extra=()):
    """A zip laid out like GitHub's archive of BROAD: broad-main/data_hdf5/*, data_mat/trials.json."""
    with zipfile.ZipFile(dest_zip, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("broad-main/README.md", "BROAD")
        zf.writestr("broad-main/example_code/process_data.py", "print()")
        for p in sorted(src_dir.iterdir()):
            folder = "data_mat" if p.name == "trials.json" else "data_hdf5"
            data = p.read_bytes()
            if p.name == corrupt_member:
                data = data[:2000]  # a truncated HDF5 inside a valid zip
            zf.writestr(f"broad-main/{folder}/{p.name}", data)
        for name, data in extra:
            zf.writestr(name, data)


def test_download_unpacks_only_data_and_verifies(tmp_path, server):
    www, url = server
    src = make_broad_dir(tmp_path / "src", ["01_a", "02_b"], ["01_a", "02_b", "03_c"])
    build_archive(src, www / "main.zip")
    dest = download_broad(tmp_path / "data" / "broad", url=f"{url}/main.zip")
    assert sorted(p.name for p in dest.iterdir()) == ["01_a.hdf5", "02_b.hdf5", "trials.json"]
    idx = DatasetIndex.from_dir(dest)
    assert list(idx.available) == ["01_a", "02_b"] and idx.missing == ["03_c"]
    assert (dest / "01_a.hdf5").read_bytes() == (src / "01_a.hdf5").read_bytes()


def test_corrupt_trial_in_archive_leaves_nothing_half_written(tmp_path, server):
    www, url = server
    src = make_broad_dir(tmp_path / "src", ["01_a", "02_b"], ["01_a", "02_b"])
    build_archive(src, www / "main.zip", corrupt_member="02_b.hdf5")
    dest = tmp_path / "out"
    with pytest.raises(DataError, match=r"02_b\.hdf5: downloaded trial fails verification"):
        download_broad(dest, url=f"{url}/main.zip")
    files = sorted(p.name for p in dest.iterdir())
    assert files == ["01_a.hdf5"]  # the verified one stays; no .part, no archive, no broken 02_b


def test_http_error_and_non_zip_are_clear(tmp_path, server):
    www, url = server
    with pytest.raises(DataError, match="download failed.*404"):
        download_broad(tmp_path / "o1", url=f"{url}/missing.zip")
    (www / "page.zip").write_text("<html>not a zip</html>")
    with pytest.raises(DataError, match="not a zip archive"):
        download_broad(tmp_path / "o2", url=f"{url}/page.zip")
    assert list((tmp_path / "o2").iterdir()) == []
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("other-main/README.md", "x")
    (www / "empty.zip").write_bytes(buf.getvalue())
    with pytest.raises(DataError, match="holds no BROAD data"):
        download_broad(tmp_path / "o3", url=f"{url}/empty.zip")


def test_cli_download(tmp_path, server, capsys):
    from togglecf.cli.main import main
    www, url = server
    src = make_broad_dir(tmp_path / "src", ["01_a"], ["01_a"])
    build_archive(src, www / "main.zip")
    assert main(["download", str(tmp_path / "d"), "--url", f"{url}/main.zip"]) == 0
    assert "--data" in capsys.readouterr().out
    assert json.loads((tmp_path / "d" / "trials.json").read_text())["trials"]

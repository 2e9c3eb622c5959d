"""The code a run used, as the generated tables name it."""
import subprocess

from togglecf.core.provenance import source_revision


def _git(cwd, *args):
    subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True)


def test_source_revision_names_the_commit_and_uncommitted_changes(tmp_path):
    _git(tmp_path, "init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    _git(tmp_path, "add", "a.py")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "one")
    sha = subprocess.run(["git", "rev-parse", "--short=7", "HEAD"], cwd=tmp_path, capture_output=True,
                         text=True, check=True).stdout.strip()
    assert source_revision(tmp_path) == f"commit {sha}"
    (tmp_path / "b.py").write_text("untracked\n")  # a file git does not track changes nothing
    assert source_revision(tmp_path) == f"commit {sha}"
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "t.md").write_text("table\n")
    _git(tmp_path, "add", "docs/t.md")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "two")
    sha = subprocess.run(["git", "rev-parse", "--short=7", "HEAD"], cwd=tmp_path, capture_output=True,
                         text=True, check=True).stdout.strip()
    (tmp_path / "docs" / "t.md").write_text("a table a run rewrote\n")  # generated docs are not the code
    assert source_revision(tmp_path) == f"commit {sha}"
    (tmp_path / "a.py").write_text("x = 2\n")
    assert source_revision(tmp_path) == f"commit {sha} with uncommitted changes"
    assert source_revision(tmp_path / "docs") == f"commit {sha} with uncommitted changes"  # from a subfolder too


def test_source_revision_outside_a_checkout_names_the_version(tmp_path):
    assert source_revision(tmp_path).startswith("togglecf ")

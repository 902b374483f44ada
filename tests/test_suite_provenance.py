"""A suite result names the code that ran: the checkout its process started with, and whether it moved since."""

import shutil
import subprocess

import pytest

from ddp.suite import provenance

pytestmark = pytest.mark.skipif(shutil.which("git") is None, reason="needs git")


def git(repo, *args):
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=repo, check=True,
                   capture_output=True)


@pytest.fixture
def repo(tmp_path):
    (tmp_path / "ddp").mkdir()
    (tmp_path / "ddp" / "a.py").write_text("x = 1\n")
    (tmp_path / "README.md").write_text("readme\n")
    git(tmp_path, "init", "-q")
    git(tmp_path, "add", ".")
    git(tmp_path, "commit", "-q", "-m", "first")
    return tmp_path


def test_checkout_counts_the_package_source_only(repo):
    clean = provenance.checkout(repo)
    assert len(clean["commit"]) == 40 and clean["dirty"] is False
    (repo / "README.md").write_text("results written while a suite runs\n")  # outside ddp/: not the code
    assert provenance.checkout(repo) == clean
    (repo / "ddp" / "a.py").write_text("x = 2\n")
    edited = provenance.checkout(repo)
    assert edited["dirty"] is True and edited["commit"] == clean["commit"] and edited["source"] != clean["source"]
    (repo / "ddp" / "a.py").write_text("x = 3\n")  # another edit of the same file is another source
    assert provenance.checkout(repo)["source"] != edited["source"]
    (repo / "ddp" / "a.py").write_text("x = 1\n")
    (repo / "ddp" / "new.py").write_text("y = 1\n")  # a new, untracked module is part of what runs
    untracked = provenance.checkout(repo)
    assert untracked["dirty"] is True
    (repo / "ddp" / "new.py").write_text("y = 2\n")  # and so is its content
    assert provenance.checkout(repo)["source"] != untracked["source"]
    assert provenance.checkout(repo / "ddp") == {}  # not a checkout's root: nothing to say


def test_code_version_is_the_checkout_the_process_started_with(repo, monkeypatch):
    monkeypatch.setattr(provenance, "_PROCESS", None)
    monkeypatch.setattr(provenance, "_root", lambda: repo)
    started = provenance.process_code()
    assert provenance.code_version() == {"ddp": started["ddp"], "commit": started["commit"], "dirty": False}

    (repo / "README.md").write_text("a results commit\n")
    git(repo, "commit", "-q", "-am", "results only")  # a new commit, but the package source is the same
    assert "changed_during_run" not in provenance.code_version()
    (repo / "ddp" / "a.py").write_text("x = 2\n")
    git(repo, "commit", "-q", "-am", "code")
    now = provenance.checkout(repo)["commit"]
    version = provenance.code_version()
    assert version["commit"] == started["commit"]  # what this process imported, not the checkout now
    assert version["changed_during_run"] is True and version["commit_now"] == now and version["dirty_now"] is False
    assert provenance.process_code() == started  # the first look stays


def test_an_installed_package_reports_its_version_only(tmp_path, monkeypatch):
    monkeypatch.setattr(provenance, "_PROCESS", None)
    monkeypatch.setattr(provenance, "_root", lambda: tmp_path)
    assert set(provenance.code_version()) == {"ddp"}


def test_the_first_look_imports_the_whole_package(tmp_path, monkeypatch):
    """Every module is imported when the process first looks at its code, so that an evaluation an hour later
    does not import a newer module beside the older ones (a changed interface failed two suite runs)."""
    import sys

    pkg = tmp_path / "lazypkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "eager.py").write_text("")
    (pkg / "sub" / "lazy.py").write_text("VERSION = 1\n")
    (pkg / "needs_driver.py").write_text("import a_driver_that_is_not_installed\n")
    (pkg / "broken").mkdir()
    (pkg / "broken" / "__init__.py").write_text("raise RuntimeError('a subpackage that fails to import')\n")
    (pkg / "__main__.py").write_text("raise SystemExit('the CLI ran')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in [m for m in sys.modules if m.startswith("lazypkg")]:
        monkeypatch.delitem(sys.modules, name)
    assert sorted(provenance.load_package("lazypkg")) == ["lazypkg.broken", "lazypkg.needs_driver"]
    assert "lazypkg.sub.lazy" in sys.modules and "lazypkg.__main__" not in sys.modules
    (pkg / "sub" / "lazy.py").write_text("VERSION = 2\n")  # the checkout moves on
    import importlib

    assert importlib.import_module("lazypkg.sub.lazy").VERSION == 1  # the process keeps what it loaded
    for name in [m for m in sys.modules if m.startswith("lazypkg")]:
        monkeypatch.delitem(sys.modules, name)

    calls = []
    monkeypatch.setattr(provenance, "_PROCESS", None)
    monkeypatch.setattr(provenance, "_root", lambda: tmp_path)
    monkeypatch.setattr(provenance, "load_package", lambda package="ddp": calls.append(package) or [])
    provenance.process_code()
    provenance.process_code()
    assert calls == ["ddp"]  # on the first look only

"""Which code produced a suite result: what to check out to redo it, and whether that is certain.

A Python process runs the code it imported. A suite's worker imports the package when it starts and may run
for hours while the checkout moves on (commits, edits), so the checkout at the end of a run is not what ran.
:func:`code_version` therefore reports the checkout as this process found it on its first call
(:func:`process_code`, made when a pool worker starts, else at the start of the first run), and that call
imports every module of the package (many are otherwise imported lazily, on first use: an evaluation an
hour into a run would import the newer code beside the older, and a changed interface between them
failed both evaluations of a suite). It still says when the package's source has changed since.

In a git checkout the state is the commit and whether the package's own source (``ddp/``, untracked files
included) differs from it; results files, READMEs and notes written while a suite runs do not count.
An installed package reports its version only.
"""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

__all__ = ["checkout", "code_version", "load_package", "process_code"]

_PROCESS: dict | None = None  # this process's first look at its code (see process_code)


def checkout(root: Path, package: str = "ddp") -> dict:
    """The state of the git checkout at ``root``: ``commit``, ``dirty`` (the ``package`` folder differs
    from the commit, untracked files included) and ``source``, a digest of the package's source itself (its
    tree in the commit and the difference from it): equal for a commit that changed only other files,
    different for any two edits of the package. Empty outside a git checkout or without git."""
    if not (root / ".git").exists():  # an installed package: a git repository above it is not its source
        return {}

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)

    try:
        commit = git("rev-parse", "HEAD")
        tree = git("rev-parse", f"HEAD:{package}")
        diff = git("diff", "HEAD", "--", package)
        untracked = git("ls-files", "--others", "--exclude-standard", "--", package)
    except (OSError, subprocess.SubprocessError):
        return {}
    if commit.returncode != 0:
        return {}
    out = {"commit": commit.stdout.strip()}
    if diff.returncode == 0 and untracked.returncode == 0 and tree.returncode == 0:
        contents = hashlib.sha256()
        for name in untracked.stdout.splitlines():  # untracked modules run too: their content counts
            try:
                contents.update(name.encode() + b"\0" + (root / name).read_bytes())
            except OSError:
                contents.update(name.encode() + b"\0unreadable")
        source = "\0".join((tree.stdout.strip(), diff.stdout, untracked.stdout, contents.hexdigest()))
        out["dirty"] = bool(diff.stdout.strip() or untracked.stdout.strip())
        out["source"] = hashlib.sha256(source.encode()).hexdigest()[:16]
    return out


def _root() -> Path:
    import ddp

    return Path(ddp.__file__).resolve().parent.parent


def load_package(package: str = "ddp") -> list[str]:
    """Import every module of ``package`` now, so that this process runs one version of it whatever the
    checkout becomes; returns the modules that could not be imported (an optional dependency missing: they
    fail where they are used, as before)."""
    import importlib
    import pkgutil

    root = importlib.import_module(package)
    failed = []
    # onerror: a subpackage whose __init__ fails is listed, not raised (walk_packages imports it to look inside)
    for module in pkgutil.walk_packages(root.__path__, f"{package}.", onerror=failed.append):
        if module.name.rsplit(".", 1)[-1] == "__main__":  # the CLI entry point runs when imported
            continue
        try:
            importlib.import_module(module.name)
        except Exception:  # noqa: BLE001 - e.g. a real-robot backend without its driver installed
            failed.append(module.name)
    return list(dict.fromkeys(failed))  # a failing subpackage is reported by walk_packages and by its import


def process_code() -> dict:
    """The package version and checkout this process started with (computed on the first call, which also
    imports the whole package: :func:`load_package`)."""
    global _PROCESS
    if _PROCESS is None:
        import ddp

        _PROCESS = {"ddp": ddp.__version__, **checkout(_root())}
        load_package()
    return dict(_PROCESS)


def code_version() -> dict:
    """What produced a result made in this process: :func:`process_code`, plus ``changed_during_run: true``
    and the checkout now (``commit_now``, ``dirty_now``) when the package's source is no longer what the
    process started with."""
    out = process_code()
    if "commit" not in out:
        return out
    now = checkout(_root())
    if now.get("source") is not None and now["source"] != out.get("source"):
        out.update(changed_during_run=True, commit_now=now.get("commit"), dirty_now=now.get("dirty"))
    out.pop("source", None)
    return out

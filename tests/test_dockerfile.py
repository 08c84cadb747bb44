"""The container build, as far as it can run here (no image registry is reachable, so no real
`docker build`): the Dockerfile's COPY sources survive .dockerignore by Docker's own rules,
and the files they let in are enough to install the project and start `phd serve`.

The Dockerfile is read with Docker's own parser (the `dockerfile` package wraps BuildKit's Go
parser) and the context is filtered with the Docker SDK's `exclude_paths`, the function
`docker build` from Python sends the context through (it implements `**`, `!` re-includes and
parent-directory matches as the daemon does), so neither is a regex of ours.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import dockerfile
import httpx
from docker.utils.build import exclude_paths

from support.fixtures import svc_free_port

ROOT = Path(__file__).resolve().parents[1]


def ignore_patterns(text: str) -> list[str]:
    """.dockerignore lines as the Docker SDK's build() reads them: stripped, no blanks or comments."""
    return [line.strip() for line in text.splitlines() if line.strip() and not line.strip().startswith("#")]


def copy_instructions(path: Path) -> list[tuple[list[str], str]]:
    """(sources, destination) of every COPY (and ADD) of the Dockerfile."""
    found = []
    for command in dockerfile.parse_file(str(path)):
        if command.cmd.lower() in ("copy", "add"):
            assert not any(flag.startswith("--from") for flag in command.flags), "a COPY from another stage"
            *sources, destination = command.value
            found.append((sources, destination))
    return found


def context_files(root: Path, patterns: list[str]) -> set[str]:
    """The regular files of `root` that .dockerignore lets into the build context."""
    return {p for p in exclude_paths(str(root), list(patterns)) if (root / p).is_file()}


def missing_sources(root: Path, patterns: list[str], copies: list[tuple[list[str], str]]) -> list[str]:
    """COPY sources that bring no file into the image (the build stops at such a COPY)."""
    let_in = context_files(root, patterns)
    return [source for sources, _ in copies for source in sources
            if not any(f == source or f.startswith(source.rstrip("/") + "/") for f in let_in)]


def image_tree(root: Path, patterns: list[str], copies: list[tuple[list[str], str]], target: Path) -> list[str]:
    """Copy exactly what the COPY instructions put into WORKDIR: a directory source's files
    into the destination, a file source into a destination ending in '/'. Returns the paths."""
    let_in = sorted(context_files(root, patterns))
    written = []
    for sources, destination in copies:
        for source in sources:
            source = source.rstrip("/")
            for rel in let_in:
                if rel == source:
                    dest = Path(destination) / Path(rel).name if destination.endswith("/") else Path(destination)
                elif rel.startswith(source + "/"):
                    dest = Path(destination) / Path(rel).relative_to(source)
                else:
                    continue
                out = target / dest
                out.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(root / rel, out)
                written.append(str(dest))
    return written


def test_every_copy_source_survives_dockerignore() -> None:
    copies = copy_instructions(ROOT / "Dockerfile")
    assert {s for sources, _ in copies for s in sources} >= {"pyproject.toml", "phd_core", "phd_cli", "service"}
    patterns = ignore_patterns((ROOT / ".dockerignore").read_text())
    assert missing_sources(ROOT, patterns, copies) == []
    let_in = context_files(ROOT, patterns)
    assert not any("__pycache__" in f or f.endswith(".pyc") for f in let_in)
    assert not any(f.startswith(("tests/", ".venv/", "bench/", ".git/")) for f in let_in)


def test_the_check_finds_a_source_dockerignore_leaves_out() -> None:
    """The bug of issue 33: `phd_cli` copied but not let back in after `**`."""
    copies = copy_instructions(ROOT / "Dockerfile")
    patterns = [p for p in ignore_patterns((ROOT / ".dockerignore").read_text()) if p.rstrip("/") != "!phd_cli"]
    assert missing_sources(ROOT, patterns, copies) == ["phd_cli"]
    # A later pattern excludes again what an earlier `!` let in, as in Docker (the last match decides).
    assert missing_sources(ROOT, [*patterns, "!phd_cli/", "phd_cli/**"], copies) == ["phd_cli"]


def test_the_copied_files_install_the_project_and_serve(tmp_path: Path) -> None:
    """Only the files the image gets: `pip install .` there (into a fresh venv that borrows the
    test environment's third-party packages, torch included, through a .pth path line: no
    download, and the checkout itself is not importable), then `phd serve` from that install."""
    copies = copy_instructions(ROOT / "Dockerfile")
    patterns = ignore_patterns((ROOT / ".dockerignore").read_text())
    app = tmp_path / "app"
    written = image_tree(ROOT, patterns, copies, app)
    assert "phd_cli/__init__.py" in written and "service/page/index.html" in written

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    # A plain path line: the test venv's packages, but not its .pth files (the editable install of the checkout).
    Path(site, "borrowed.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PHD_", "PYTHON"))}
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
                    "--no-build-isolation", "--no-index", "--disable-pip-version-check", str(app)],
                   check=True, cwd=tmp_path, env=env, capture_output=True)
    where = subprocess.run([python, "-c", "import phd_cli, phd_core, service, client; "
                            "print('\\n'.join(m.__file__ for m in (phd_cli, phd_core, service, client)))"],
                           check=True, cwd=tmp_path, env=env, capture_output=True, text=True).stdout.split()
    assert all(Path(f).is_relative_to(site) for f in where), where

    port = svc_free_port()
    log = tmp_path / "serve.log"
    with open(log, "wb") as out:
        server = subprocess.Popen([venv / "bin" / "phd", "serve", "--port", str(port), "--data-dir",
                                   str(tmp_path / "data"), "--log-level", "warning"],
                                  cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline, health = time.monotonic() + 60, None
        while health is None and server.poll() is None and time.monotonic() < deadline:
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/health", timeout=1)
            except httpx.TransportError:
                time.sleep(0.2)
        assert health is not None and health.status_code == 200, log.read_text()
        page = httpx.get(f"http://127.0.0.1:{port}/ui/", timeout=5)     # package data came along
        assert page.status_code == 200 and "<html" in page.text.lower()
    finally:
        server.terminate()
        server.wait(timeout=30)
    first = log.read_text().splitlines()[0]
    assert first.startswith(f"phd serve: the page: http://127.0.0.1:{port}/ui/"), first


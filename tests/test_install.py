"""The install-time build of the native kernels (setup.py), as a user meets it.

* No compiler: ``pip install`` still succeeds, ``import difftex`` works on
  the torch path and warns once, naming what is missing.
* A build killed with SIGKILL leaves nothing that stops the next install:
  the reinstall builds and the kernels load.
* First use compiles nothing: a fresh process runs ``import difftex``, a
  trilinear ``sample`` and a ``rasterize`` at 256^2 within a few seconds.

The two install tests copy the project to a temporary folder and install it
into a virtual environment that sees this one's packages (torch included),
so they take a minute or two; the first-use test runs the installed tree.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIRST_USE = """
import time, torch
t = time.perf_counter()
import difftex
from difftex import _native
tex = torch.rand(1, 3, 256, 256)
uv = torch.rand(1, 256, 256, 2)
d = torch.full_like(uv, 1 / 256)
difftex.sample(tex, uv, filter="trilinear", uv_dx=d, uv_dy=d)
pos = torch.tensor([[-0.9, -0.9, 0.0, 1.0], [0.9, -0.9, 0.0, 1.0], [0.0, 0.9, 0.0, 1.0]])
difftex.rasterize(pos, torch.tensor([[0, 1, 2]]), (256, 256))
print("from", difftex.__file__)
print("native", _native.load() is not None, "seconds", time.perf_counter() - t)
"""


def _project_copy(dst: Path) -> Path:
    keep = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md")
    dst.mkdir()
    for name in keep:
        shutil.copy2(ROOT / name, dst / name)
    shutil.copytree(ROOT / "difftex", dst / "difftex",
                    ignore=shutil.ignore_patterns("__pycache__", "*.so", "*.pyd"))
    return dst


def _venv(path: Path) -> Path:
    """A venv that sees this environment's packages (torch, numpy, ...) after its own: a .pth file named
    to be read after the venv's own editable-install hooks, so that its difftex is the copy's."""
    import sysconfig
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True)
    py = path / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    outer = sysconfig.get_paths()["purelib"]
    Path(site, "zz_outer.pth").write_text(f"import site; site.addsitedir({outer!r})\n")
    return py


def _install(py: Path, project: Path, env: dict, timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "-e",
                           str(project)], env=env, capture_output=True, text=True, timeout=timeout)


def _run(py: Path, code: str, env: dict, cwd: Path) -> subprocess.CompletedProcess:
    # cwd outside the project copy's parent folder, so that the installed package is the one imported
    return subprocess.run([str(py), "-W", "always::RuntimeWarning", "-c", code], env=env, cwd=cwd,
                          capture_output=True, text=True, timeout=120)


@pytest.fixture()
def sandbox(tmp_path):
    if sys.platform.startswith("win"):
        pytest.skip("POSIX venv layout and signals")
    env = {k: v for k, v in os.environ.items() if k not in ("DIFFTEX_NATIVE", "PYTHONPATH")}
    return tmp_path, _venv(tmp_path / "venv"), _project_copy(tmp_path / "project"), env


@pytest.mark.timeout(600)
def test_without_a_compiler_the_install_succeeds_on_the_torch_path(sandbox):
    tmp, py, project, env = sandbox
    env = dict(env, CXX="false", CC="false")
    done = _install(py, project, env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert not list((project / "difftex").glob("_C*.so"))
    got = _run(py, FIRST_USE, env, tmp)
    assert got.returncode == 0, got.stderr
    assert f"from {project}" in got.stdout, got.stdout
    assert "native False" in got.stdout
    assert got.stderr.count("the native CPU kernels are not built") == 1, got.stderr
    assert "pip install --no-build-isolation" in got.stderr


@pytest.mark.timeout(900)
def test_a_killed_build_leaves_nothing_that_stops_the_next(sandbox):
    tmp, py, project, env = sandbox
    env = dict(env, MAX_JOBS="2")
    proc = subprocess.Popen([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "-e",
                             str(project)], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    # Kill the whole build (pip, setuptools, ninja, the compilers) part-way, as a job's time limit would.
    time.sleep(12)
    assert proc.poll() is None, "the build ended before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)
    done = _install(py, project, env, timeout=600)
    assert done.returncode == 0, done.stderr
    got = _run(py, FIRST_USE, env, tmp)
    assert got.returncode == 0, got.stderr
    assert f"from {project}" in got.stdout, got.stdout
    assert "native True" in got.stdout, got.stdout + got.stderr
    assert "not built" not in got.stderr


def test_first_use_compiles_nothing_and_takes_seconds(tmp_path):
    from difftex import _native
    if _native.load() is None:
        pytest.skip("native kernels not built")
    env = {k: v for k, v in os.environ.items() if k != "DIFFTEX_NATIVE"}
    env["PYTHONPATH"] = str(ROOT)
    env["HOME"] = str(tmp_path)  # nothing may be written to (or read from) a cache under ~
    got = _run(Path(sys.executable), FIRST_USE, env, tmp_path)
    assert got.returncode == 0, got.stderr
    assert "native True" in got.stdout
    seconds = float(got.stdout.split("seconds")[1])
    assert seconds < 10.0, got.stdout  # 3 s is the target on an idle 2-core machine (README); 10 s under load
    assert not (tmp_path / ".cache" / "torch_extensions").exists()

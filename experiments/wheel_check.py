"""One wheel, many torches: build difftex's wheel against this environment's torch, install it into fresh
virtual environments with other torch releases, and run the kernel's tests there.

The kernels use only torch's LibTorch stable ABI (targeting 2.10) and Python's limited API, so the wheel
built against the pinned torch (2.13) should load and agree with the torch path on every torch from 2.10
on, without a rebuild. Each check:

1. ``python -m build --wheel --no-isolation`` here (once), against the torch this environment has;
2. a fresh venv per torch version: ``pip install torch==V``, then the wheel with its ``test`` extra;
3. from a copy of tests/ outside the checkout (so that the installed wheel, not the source tree, is
   imported): ``difftex._native.load()`` must find the kernels, and the tests that hold the native path to
   the torch path (tests/texture/native, tests/test_native_ops.py) must pass.

Run: ``python -m experiments.wheel_check 2.10.0 2.15.0`` (default: those two). Each torch release from PyPI
is a large download (a CUDA build, several GB with its libraries); the venvs go under --work and are kept
for reruns. Prints one line per version and exits non-zero when any fails. Not part of CI, which keeps the
pinned torch.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = ["tests/texture/native", "tests/test_native_ops.py"]
PROBE = (
    "import sys, torch, difftex; from difftex import _native as n; "
    "assert n.load() is not None, 'native kernels did not load'; "
    "assert 'site-packages' in difftex.__file__, difftex.__file__; "
    "print(torch.__version__, difftex.__file__)"
)


def run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    print("+", " ".join(cmd), flush=True)
    return subprocess.run(cmd, check=True, **kw)


def build_wheel(out: Path) -> Path:
    """The wheel of this checkout, built against this interpreter's torch (no build isolation)."""
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("difftex-*.whl"):
        old.unlink()
    run([sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(out), str(ROOT)])
    wheels = sorted(out.glob("difftex-*.whl"))
    if len(wheels) != 1 or "abi3" not in wheels[0].name:
        raise SystemExit(f"expected one abi3 wheel in {out}, found {[w.name for w in wheels]}")
    return wheels[0]


def check(version: str, wheel: Path, work: Path) -> tuple[bool, str]:
    venv = work / f"torch-{version}"
    py = venv / "bin" / "python"
    # The workplace's pip may cap torch's version (a constraints file in pip's global config); the check
    # asks for exact releases, so it reads no config file.
    env = dict(os.environ, PIP_CONFIG_FILE=os.devnull)
    if not py.exists():
        run([sys.executable, "-m", "venv", str(venv)])
        run([str(py), "-m", "pip", "install", "-q", "--upgrade", "pip"], env=env)
        run([str(py), "-m", "pip", "install", "-q", f"torch=={version}"], env=env)
    run([str(py), "-m", "pip", "install", "-q", "--force-reinstall", "--no-deps", str(wheel)], env=env)
    run([str(py), "-m", "pip", "install", "-q", f"{wheel}[test]"], env=env)
    probe = subprocess.run([str(py), "-c", PROBE], cwd=work, capture_output=True, text=True)
    if probe.returncode != 0:
        return False, f"kernels did not load: {probe.stderr.strip().splitlines()[-1:]}"
    t = time.perf_counter()
    shutil.rmtree(work / "tests", ignore_errors=True)
    shutil.copytree(ROOT / "tests", work / "tests")
    res = subprocess.run([str(py), "-m", "pytest", "-q", "-p", "no:cacheprovider", *TESTS], cwd=work,
                         capture_output=True, text=True)
    summary = (res.stdout.strip().splitlines() or ["(no output)"])[-1]
    return res.returncode == 0, f"{probe.stdout.strip()}; {summary} ({time.perf_counter() - t:.0f} s)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("versions", nargs="*", default=["2.10.0", "2.15.0"], help="torch releases to check")
    ap.add_argument("--work", type=Path, default=Path("/tmp/difftex-wheel-check"), help="venvs and wheel")
    args = ap.parse_args()
    import torch

    wheel = build_wheel(args.work / "dist")
    print(f"built {wheel.name} against torch {torch.__version__}")
    failed = False
    for v in args.versions:
        ok, msg = check(v, wheel, args.work)
        failed |= not ok
        print(f"torch {v}: {'PASS' if ok else 'FAIL'}: {msg}", flush=True)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()

"""Builds difftex's native CPU kernels (``difftex/csrc``) into ``difftex._C`` at install time.

Everything else about the package is in pyproject.toml. The kernels use only torch's LibTorch stable ABI
(targeting torch 2.10) and Python's limited API (3.9), so one build, or one wheel, runs on torch 2.10 and
later and on any CPython >= 3.9 without a rebuild.

The build needs torch (>= 2.10) importable in the build environment and a C++17 compiler. Install with
``pip install --no-build-isolation .`` (or ``-e .``) into an environment that has torch already: pip's
default isolated build environment would otherwise have no torch. Where either is missing, or the compile
fails, the install still succeeds without the kernels, and ``import difftex`` warns once and runs the
torch path (the same results; the kernels are only faster).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from setuptools import setup

ROOT = Path(__file__).resolve().parent
CSRC = Path("difftex") / "csrc"
# torch 2.10's stable ABI; the hex form TORCH_TARGET_VERSION takes (major << 56 | minor << 48).
TARGET = "0x020a000000000000"
MIN_TORCH = (2, 10)


def _say(msg: str) -> None:
    # pip shows a build's output only with -v; stderr of a failed step is what users see in logs.
    print(f"difftex setup: {msg}", file=sys.stderr, flush=True)


def _extension_setup() -> dict:
    """ext_modules and cmdclass for setup(), or {} where the kernels cannot be built here."""
    if os.environ.get("DIFFTEX_BUILD_NATIVE", "1") == "0":
        _say("DIFFTEX_BUILD_NATIVE=0: not building the native kernels")
        return {}
    try:
        import torch
        from torch.utils.cpp_extension import BuildExtension, CppExtension
    except ImportError:
        _say("torch is not importable in the build environment: installing without the native kernels "
             "(install torch first, then `pip install --no-build-isolation .`)")
        return {}
    version = tuple(int(p) for p in torch.__version__.split("+")[0].split(".")[:2])
    if version < MIN_TORCH:
        _say(f"torch {torch.__version__} has no stable ABI (needs >= 2.10): installing without the native kernels")
        return {}

    class SafeBuild(BuildExtension):
        """BuildExtension that turns a failed compile into an install without the kernels (and a message)."""

        def run(self) -> None:
            try:
                super().run()
            except Exception as exc:  # no compiler, a compile error: the torch path serves
                _say(f"building the native kernels failed ({type(exc).__name__}: {exc}); installing without "
                     "them: difftex runs its torch path")

        def get_outputs(self) -> list:
            return [p for p in super().get_outputs() if os.path.exists(p)]

    # Largest translation unit first: ninja starts jobs in the order given, and on two cores the build ends
    # when the longest one does (texture/single.cpp is about 30 s of the 70 s of compiling).
    files = sorted((ROOT / CSRC).rglob("*.cpp"), key=lambda p: (-p.stat().st_size, str(p)))
    sources = [str(p.relative_to(ROOT)) for p in files]
    # One compile a core: ninja's default (cores + 2) makes the longest unit share its core.
    os.environ.setdefault("MAX_JOBS", str(len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                                          else os.cpu_count() or 1))
    if os.name == "nt":
        flags = ["/O2", "/fp:precise", "/std:c++17"]
    else:
        # No contraction into fused multiply-adds (on by default where the target has them, e.g. aarch64):
        # the kernels must round each product as the torch path does.
        # Python's own CFLAGS (which setuptools passes first) ask for -g, which adds 40 % to the compile, and
        # -fwrapv, which keeps the compiler from assuming that an index never overflows: the single-level
        # reads ran 5-10 % slower with it than the JIT build they replace. -g0 and -fno-wrapv undo both.
        flags = ["-O3", "-g0", "-fno-wrapv", "-ffp-contract=off", "-std=c++17", "-Wno-psabi"]
    ext = CppExtension(
        name="difftex._C",
        sources=sources,
        include_dirs=[str(ROOT / CSRC), str(ROOT / CSRC / "cpu")],
        extra_compile_args={"cxx": flags + [f"-DTORCH_TARGET_VERSION={TARGET}"]},
        py_limited_api=True,
    )
    return {
        "ext_modules": [ext],
        "cmdclass": {"build_ext": SafeBuild.with_options(use_ninja=True)},
        "options": {"bdist_wheel": {"py_limited_api": "cp39"}},
    }


setup(**_extension_setup())

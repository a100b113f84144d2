"""Builds the libflame wheel: the ctypes package plus the shared library, built by cargo.

`pip install bindings/python` runs `cargo build --release --lib` on the crate two folders up
(the repository root) and puts the library it reports next to `flame/__init__.py`. Cargo
decides what is stale, so a fresh `target/release/libflame.so` costs no rebuild and a stale one
is never packed. The wheel is tagged `py3-none-<platform>`: the package is pure Python, the
library is native and does not depend on Python's ABI.

Environment (all optional):
  FLAME_WHEEL_LIBRARY   pack this already-built library instead of running cargo (a build
                        for another target, or one a test has already checked)
  FLAME_CARGO_PROFILE   cargo profile to build: release (default) or dev/debug
  CARGO, CARGO_TARGET_DIR, CARGO_BUILD_TARGET and the rest of cargo's own variables apply.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from setuptools import Distribution, setup
from setuptools.command.build_py import build_py

try:  # setuptools >= 70.1 has its own; older ones need the `wheel` package's
    from setuptools.command.bdist_wheel import bdist_wheel
except ImportError:  # pragma: no cover
    from wheel.bdist_wheel import bdist_wheel

HERE = Path(__file__).resolve().parent
MANIFEST = HERE.parent.parent / "Cargo.toml"
LIBRARY_NAMES = {"win32": "flame.dll", "darwin": "libflame.dylib"}


def library_name() -> str:
    return LIBRARY_NAMES.get(sys.platform, "libflame.so")


def cargo_build() -> Path:
    """Builds the crate's library with cargo and returns the shared library it wrote."""
    if not MANIFEST.is_file():
        sys.exit(
            f"libflame: no Rust crate at {MANIFEST}: build the wheel from a libflame checkout "
            "(pip install path/to/libflame/bindings/python), or set FLAME_WHEEL_LIBRARY to a "
            "built library"
        )
    cargo = os.environ.get("CARGO", "cargo")
    profile = os.environ.get("FLAME_CARGO_PROFILE", "release")
    profile = "dev" if profile == "debug" else profile
    cmd = [cargo, "build", "--lib", "--profile", profile, "--manifest-path", str(MANIFEST),
           "--message-format", "json-render-diagnostics"]
    print("libflame:", " ".join(cmd), flush=True)
    try:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, check=True)
    except FileNotFoundError:
        sys.exit(f"libflame: `{cargo}` not found: building the wheel needs a Rust toolchain "
                 "(https://rustup.rs), or set FLAME_WHEEL_LIBRARY to a built library")
    except subprocess.CalledProcessError as e:
        sys.exit(f"libflame: cargo build failed (exit {e.returncode})")
    # The artifact cargo reports is the one it just built or found fresh, wherever the target
    # directory is (CARGO_TARGET_DIR, a --target triple).
    for line in proc.stdout.decode("utf-8", "replace").splitlines():
        if not line.startswith("{"):
            continue
        msg = json.loads(line)
        if msg.get("reason") != "compiler-artifact" or "cdylib" not in msg["target"]["kind"]:
            continue
        for f in msg["filenames"]:
            if Path(f).name == library_name():
                return Path(f)
    sys.exit(f"libflame: cargo built no {library_name()}")


class BuildPyWithLibrary(build_py):
    """build_py, then the shared library into the build tree (never into the source tree, where
    a forgotten copy would shadow newer builds)."""

    def run(self):
        super().run()
        given = os.environ.get("FLAME_WHEEL_LIBRARY")
        if given:
            lib = Path(given)
            if not lib.is_file():
                sys.exit(f"libflame: FLAME_WHEEL_LIBRARY={given!r} is not a file")
        else:
            lib = cargo_build()
        dest = Path(self.build_lib) / "flame" / library_name()
        dest.parent.mkdir(parents=True, exist_ok=True)
        print(f"libflame: packing {lib}", flush=True)
        shutil.copyfile(lib, dest)  # a plain copy: always the newest bytes, whatever the mtimes
        strip_debug(dest)


def strip_debug(path):
    """Ships the library without its debug info (about 30 of its 35 MB on Linux), as
    packaging/install.sh does; FLAME_STRIP=0 keeps it. Needs binutils' objcopy (Linux)."""
    if os.environ.get("FLAME_STRIP", "1") == "0" or not sys.platform.startswith("linux"):
        return
    objcopy = shutil.which("objcopy")
    if objcopy is None:
        print("libflame: objcopy not found, packing the library with its debug info", flush=True)
        return
    subprocess.run([objcopy, "--strip-debug", str(path)], check=True)


class NativeDistribution(Distribution):
    """Has native code (the library), so the wheel is not pure and installs into platlib."""

    def has_ext_modules(self):
        return True


class PlatformWheel(bdist_wheel):
    """A platform wheel (the library is native) for any Python 3 (it is loaded with ctypes)."""

    def get_tag(self):
        _, _, plat = super().get_tag()
        return "py3", "none", plat


setup(
    distclass=NativeDistribution,
    cmdclass={"build_py": BuildPyWithLibrary, "bdist_wheel": PlatformWheel},
)

#!/usr/bin/env python3
"""Build a wheelhouse for installing msps on a machine with no package registry (a cluster's compute
node, the GPU test machine): run it on a connected machine, copy the folder, then on the target

    python3 -m pip install --no-index --find-links WHEELHOUSE msps   # or: WHEELHOUSE/*.whl

Why a script: the Mitsuba wheel alone is 62.6 MB, most of it plugins and variants msps never loads.
The wheelhouse pins exactly the versions installed here (the ones the tests passed with), skips what
the target already has (`--have`, default: what a PyTorch GPU image ships), and rewrites the Mitsuba
wheel to the variants and plugins msps uses (`slim_mitsuba`), so the whole set moves in ~40 MB.

    python scripts/build_wheelhouse.py --out wheelhouse                     # this machine's Python
    python scripts/build_wheelhouse.py --out .whl --python 3.12 --platform manylinux_2_28_x86_64

Each problem (pip cannot find a wheel, a package not installed here) is one line naming the package,
exit 1, and the output folder is left as it was.
"""
from __future__ import annotations

import argparse
import ast
import base64
import hashlib
import importlib.metadata as md
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# What a PyTorch GPU image (and the H200 test machine, ../shared/gpu-notes.md) already provides.
HAVE = ("torch", "numpy", "scipy", "h5py", "matplotlib", "typer", "rich", "tqdm", "pillow", "click",
        "typing-extensions", "markdown-it-py", "mdurl", "pygments", "shellingham", "contourpy", "cycler",
        "fonttools", "kiwisolver", "packaging", "pyparsing", "python-dateutil", "six", "filelock",
        "fsspec", "jinja2", "markupsafe", "networkx", "sympy", "mpmath", "setuptools", "triton",
        "annotated-doc")
# hdf5plugin (45 MB) is needed only to read/write zstd or Blosc2 shards; leave it out with --no-hdf5plugin.
EXTRAS = ("train",)

# Mitsuba variants msps renders with (render/variant.py PREFERRED); the rest are dropped.
VARIANTS = ("cuda_ad_rgb", "cuda_ad_spectral", "llvm_ad_rgb", "llvm_ad_spectral", "scalar_rgb", "scalar_spectral")
# Plugins msps loads (measured from /proc/self/maps over every preset family, ../shared/gpu-notes.md),
# those its variant probe and tests load, and the sampler/sensor/shape choices a config may name.
PLUGINS = ("blendbsdf", "box", "d65", "diffuse", "directional", "envmap", "hdrfilm", "independent", "merge",
           "multijitter", "orthographic", "path", "plastic", "point", "principled", "regular", "roughconductor",
           "roughplastic", "srgb", "uniform",  # the measured 20
           "sphere", "constant", "direct",  # the variant probe
           "stratified", "ldsampler", "orthogonal", "perspective", "specfilm", "irregular", "bitmap",
           "conductor", "twosided", "rectangle", "area", "obj", "ply", "instance", "shapegroup", "aov",
           "gaussian", "tent")  # reconstruction filters: hdrfilm's default is gaussian
DROP_DIRS = ("mitsuba/include/", "mitsuba/cmake/", "mitsuba/data/sunsky/")


def _canon(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def closure(roots: list[str], have: set[str]) -> dict[str, str]:
    """{distribution: installed version} for `roots` and everything they require (extras not taken),
    minus `have`; read from this environment's metadata so the pins are what was tested here."""
    out: dict[str, str] = {}
    todo = list(roots)
    while todo:
        req = todo.pop()
        name = _canon(re.split(r"[\s\[<>=!~;(]", req.strip(), maxsplit=1)[0])
        if name in out or name in have:
            continue
        try:
            dist = md.distribution(name)
        except md.PackageNotFoundError:
            sys.exit(f"error: {name} is required but not installed here; run scripts/setup.sh first")
        out[name] = dist.version
        for r in dist.requires or []:
            if "extra ==" not in r:
                todo.append(r)
    return out


def msps_requirements(extras: tuple[str, ...]) -> list[str]:
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"])
    for e in extras:
        reqs += project["optional-dependencies"][e]
    return reqs


def _record_line(name: str, data: bytes) -> str:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return f"{name},sha256={digest},{len(data)}"


_VARIANT_MOD = re.compile(r"^mitsuba/((?:scalar|llvm_ad|cuda_ad)_\w+)\.cpython-[^/]+\.so$")
_PLUGIN_SO = re.compile(r"^mitsuba/plugins/(\w+)\.so$")


def keeps(name: str, variants=VARIANTS, plugins=PLUGINS) -> bool:
    """Does the slim Mitsuba keep file `name` (a path inside the wheel, 'mitsuba/...')?"""
    m, p = _VARIANT_MOD.match(name), _PLUGIN_SO.match(name)
    return not ((m and m.group(1) not in variants) or (p and p.group(1) not in plugins)
                or name.startswith(DROP_DIRS) or name.endswith(".pyi")
                or (name == "mitsuba/data/srgb.coeff" and not any("spectral" in v for v in variants)))


def slim_mitsuba(src: Path, dst: Path, variants=VARIANTS, plugins=PLUGINS) -> tuple[int, int]:
    """Rewrite the Mitsuba wheel keeping `variants` and `plugins` (each plugin .so holds every variant,
    so plugins are kept or dropped whole); its config.py lists only the kept variants (`mi.variants()`
    still names every variant of the build: a dropped one fails `set_variant` with ModuleNotFoundError,
    which the variant probe reports). srgb.coeff (8.9 MB) stays only when a spectral variant does. Returns (bytes in, out)."""
    record_name = None
    lines = []
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
        for info in zin.infolist():
            n = info.filename
            if n.endswith(".dist-info/RECORD"):
                record_name = n
                continue
            if not keeps(n, variants, plugins):
                continue
            data = zin.read(n)
            if n == "mitsuba/config.py":
                data = re.sub(rb"MI_VARIANTS = \[[^\]]*\]",
                              ("MI_VARIANTS = " + repr([v for v in _variants_in(data) if v in variants])).encode(), data)
            zout.writestr(info, data)
            lines.append(_record_line(n, data))
        if record_name is None:
            raise ValueError(f"{src}: not a wheel (no RECORD)")
        lines.append(f"{record_name},,")
        zout.writestr(record_name, "\n".join(lines) + "\n")
    return src.stat().st_size, dst.stat().st_size


def _variants_in(config_py: bytes) -> list[str]:
    m = re.search(rb"MI_VARIANTS = (\[[^\]]*\])", config_py)
    return ast.literal_eval(m.group(1).decode()) if m else []  # a list of strings written by Mitsuba's build


def download(pins: dict[str, str], dest: Path, python: str | None, platforms: list[str]) -> None:
    cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "-d", str(dest)]
    if python:
        cmd += ["--python-version", python, "--implementation", "cp"]
        for p in platforms:
            cmd += ["--platform", p]
    for name, ver in sorted(pins.items()):
        r = subprocess.run(cmd + [f"{name}=={ver}"], capture_output=True, text=True)
        if r.returncode:
            why = (r.stderr.strip().splitlines() or ["pip failed"])[-1]
            sys.exit(f"error: no wheel of {name}=={ver} for python {python or 'here'}: {why}")


def build_msps(dest: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                        "-w", str(dest), str(ROOT)], capture_output=True, text=True)
    if r.returncode:
        sys.exit(f"error: building the msps wheel failed: {(r.stderr.strip().splitlines() or ['?'])[-1]}")


def have_set(arg: str) -> set[str]:
    """The distributions `--have` names (canonical), plus the default `HAVE` when it starts with '+'."""
    named = {_canon(h) for h in arg.lstrip("+").split(",") if h}
    return named | ({_canon(h) for h in HAVE} if arg.startswith("+") else set())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="wheelhouse folder (replaced when complete)")
    ap.add_argument("--python", help="target Python, e.g. 3.12 (default: this interpreter's, this platform)")
    ap.add_argument("--platform", action="append", default=None,
                    help="target platform tag(s) (default with --python: manylinux x86_64 tags)")
    ap.add_argument("--have", default=",".join(HAVE), help="comma-separated distributions the target already has "
                    "(a leading '+' adds them to the default list, e.g. +kornia-rs,colour-science)")
    ap.add_argument("--no-hdf5plugin", action="store_true", help="leave out hdf5plugin (45 MB; lzf/gzip shards only)")
    ap.add_argument("--no-msps", action="store_true", help="dependencies only (the target runs msps from a checkout)")
    ap.add_argument("--full-mitsuba", action="store_true", help="keep the Mitsuba wheel whole")
    ap.add_argument("--variants", default=",".join(VARIANTS),
                    help="Mitsuba variants to keep (a GPU node without libLLVM: cuda_ad_rgb,cuda_ad_spectral)")
    a = ap.parse_args(argv)
    platforms = a.platform or ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64",
                               "manylinux2014_x86_64"]
    have = have_set(a.have)
    if a.no_hdf5plugin:
        have.add("hdf5plugin")
    pins = closure(msps_requirements(EXTRAS), have)
    tmp = Path(tempfile.mkdtemp(prefix=".wheelhouse-", dir=a.out.resolve().parent))
    try:
        download(pins, tmp, a.python, platforms)
        if not a.full_mitsuba:
            for whl in tmp.glob("mitsuba-*.whl"):
                slim = whl.with_suffix(".slim")
                before, after = slim_mitsuba(whl, slim, variants=tuple(v for v in a.variants.split(",") if v))
                slim.replace(whl)
                print(f"mitsuba wheel slimmed: {before / 1e6:.1f} MB -> {after / 1e6:.1f} MB")
        if not a.no_msps:
            build_msps(tmp)
        if a.out.exists():
            shutil.rmtree(a.out)
        tmp.rename(a.out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    total = sum(f.stat().st_size for f in a.out.glob("*.whl"))
    print(f"{a.out}: {len(list(a.out.glob('*.whl')))} wheels, {total / 1e6:.1f} MB "
          f"({', '.join(sorted(p.name.split('-')[0] for p in a.out.glob('*.whl')))})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

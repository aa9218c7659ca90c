#!/usr/bin/env bash
# Wheel-install smoke test (run by `make test`): proves that the wheel built from the committed
# files is complete, without the network and in seconds.
#  1. build the wheel from a copy of the git-tracked (and untracked, not ignored) files only, so
#     nothing stray in the work tree (build/, *.egg-info, an editable install) can hide a gap;
#  2. check that it holds every module (icbtool/ and the app's icbtool_gui/), every shader and the
#     console script;
#  3. install it (--no-deps) into a throwaway venv that sees .venv's site-packages as a plain path
#     (its editable icbtool finder is NOT activated), check that `icbtool` is imported from the
#     wheel, and run `icbtool --help` and a tiny render from a folder outside the repository.
# A fresh `pip install .` with its dependencies (network, minutes) is what the README's install
# section describes; tests/test_packaging.py checks that every runtime import is declared.
set -euo pipefail
cd "$(dirname "$0")/.."
REPO=$(pwd)
PY=${PY:-$REPO/.venv/bin/python}
TMP=$(mktemp -d "${TMPDIR:-/tmp}/icbtool-wheel-smoke.XXXXXX")
trap 'rm -rf "$TMP"' EXIT

echo "wheel smoke: building the wheel from the tracked files"
mkdir "$TMP/src"
git ls-files -z --cached --others --exclude-standard | while IFS= read -r -d '' f; do
  [ -e "$f" ] && printf '%s\0' "$f"  # skip files deleted but not yet committed
done | tar -c --null -T - -f - | tar -x -C "$TMP/src"
# the web client's bundle is built (`make web`), not tracked: it must be in the wheel all the same
test -s icbtool/web/bundle/app.js || { echo "wheel smoke: no icbtool/web/bundle: run make web" >&2; exit 1; }
cp -r icbtool/web/bundle "$TMP/src/icbtool/web/bundle"
(cd "$TMP/src" && "$PY" -m pip wheel -q --disable-pip-version-check --no-deps \
  --no-build-isolation --no-index -w "$TMP/dist" . >/dev/null)
WHEEL=$(ls "$TMP"/dist/icbtool-*.whl)

echo "wheel smoke: checking $(basename "$WHEEL")"
"$PY" - "$WHEEL" "$TMP/src" <<'EOF'
import sys
import zipfile
from pathlib import Path

wheel, src = sys.argv[1], Path(sys.argv[2])
names = set(zipfile.ZipFile(wheel).namelist())
# icbtool and the desktop app's package icbtool_gui/ (imported only by `icbtool gui`)
want = {
    p.relative_to(src).as_posix()
    for pkg in ("icbtool", "icbtool_gui")
    for p in (src / pkg).rglob("*")
    if p.is_file()
}
want = {n for n in want if "__pycache__" not in n}
missing = sorted(want - names)
assert not missing, f"the wheel lacks {missing}"
# no top-level package with a generic name (a `gui` in site-packages collides with others')
tops = {n.split("/", 1)[0] for n in names if not n.split("/", 1)[0].endswith((".dist-info", ".data"))}
assert tops == {"icbtool", "icbtool_gui"}, f"the wheel installs top-level {sorted(tops)}"
shaders = [n for n in names if n.startswith("icbtool/raster/shaders/")]
assert len(shaders) >= 6, f"shaders not packaged: {shaders}"
web = {"icbtool/web/index.html", "icbtool/web/bundle/app.js", "icbtool/web/bundle/ort-wasm-simd-threaded.wasm"}
assert web <= names, f"the web client is not packaged: {sorted(web - names)}"
ep = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
assert "icbtool = icbtool.cli:main" in zipfile.ZipFile(wheel).read(ep).decode(), "no console script"
meta = zipfile.ZipFile(wheel).read(next(n for n in names if n.endswith(".dist-info/METADATA")))
requires = [ln for ln in meta.decode().splitlines() if ln.startswith("Requires-Dist:")]
assert not any("pyrender" in r.lower() for r in requires), requires
print(f"  {len(want)} package files present, {len(shaders)} shaders, console script, "
      f"{len(requires)} Requires-Dist")
EOF

echo "wheel smoke: installing into a throwaway venv"
"$PY" -m venv --without-pip "$TMP/venv"
SITE=$("$TMP/venv/bin/python" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
"$PY" -m pip --python "$TMP/venv/bin/python" install -q --disable-pip-version-check --no-deps \
  --no-index "$WHEEL" >/dev/null
# .venv's packages as a plain path entry: a .pth line adds the folder without running its .pth
# files, so .venv's editable icbtool finder stays off and only the wheel provides icbtool.
"$PY" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])" >"$SITE/zz_dotvenv.pth"

cd "$TMP"  # outside the repository
"$TMP/venv/bin/python" - "$SITE" <<'EOF'
import sys

import icbtool

site = sys.argv[1]
assert icbtool.__file__.startswith(site), f"icbtool imported from {icbtool.__file__}, not {site}"
print(f"  icbtool {icbtool.__version__} from {icbtool.__file__}")
EOF
"$TMP/venv/bin/icbtool" --help >/dev/null
"$TMP/venv/bin/icbtool" gui --help >/dev/null
"$TMP/venv/bin/python" -c "from icbtool.net import web; web.check_bundle(); import sys; assert str(web.WEB_ROOT).startswith(sys.argv[1])" "$SITE"
"$TMP/venv/bin/python" -c "import icbtool_gui as g, sys; assert g.__file__.startswith(sys.argv[1]), g.__file__" "$SITE"
ICBTOOL_GL_BACKEND=${ICBTOOL_GL_BACKEND:-osmesa} "$TMP/venv/bin/icbtool" render cornell_box \
  --out "$TMP/render" --height 32 --buffers dl,depth --no-png
for f in dl.exr depth.exr mask.exr summary.json; do
  test -s "$TMP/render/$f" || { echo "wheel smoke: render wrote no $f" >&2; exit 1; }
done
echo "wheel smoke: ok"

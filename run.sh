#!/bin/sh
# Set up (or reuse) .venv/ at the repository root from requirements.lock, then run a job.
#   sh run.sh demo        -> .venv/bin/hapticproxy demo
#   sh run.sh test [ARGS] -> the test suite (pytest ARGS)
#   sh run.sh <any hapticproxy subcommand ...>
#   sh run.sh --server-only JOB  -> the server alone (requirements-server.lock: no engines, GUI, plots,
#                                   viewer or test tools; what deploy/ installs), then JOB
set -eu
cd "$(dirname "$0")"
ROOT=$(pwd)
PY=${PYTHON:-}
if [ -z "$PY" ]; then
  if command -v python3.11 >/dev/null 2>&1; then PY=python3.11; else PY=python3; fi
fi
"$PY" -c 'import sys; sys.exit(0 if sys.version_info[:2] == (3, 11) else 1)' || {
  echo "run.sh: Python 3.11 is required (found: $("$PY" --version 2>&1))" >&2; exit 2; }

LOCK=requirements.lock
if [ "${1:-}" = "--server-only" ]; then
  LOCK=requirements-server.lock
  shift
fi
VENV="$ROOT/.venv"
STAMP="$VENV/.hapticproxy-installed"
WANT="$LOCK $(cat "$LOCK" pyproject.toml | cksum | cut -d' ' -f1)"
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  echo "run.sh: installing pinned dependencies into .venv/ (log: .venv/install.log) ..." >&2
  if ! { "$VENV/bin/python" -m pip install --disable-pip-version-check -r "$LOCK" &&
         "$VENV/bin/python" -m pip install --disable-pip-version-check --no-deps --no-build-isolation -e .; \
       } >"$VENV/install.log" 2>&1; then
    tail -n 30 "$VENV/install.log" >&2
    echo "run.sh: installation failed (full log: .venv/install.log)" >&2
    exit 1
  fi
  echo "$WANT" > "$STAMP"
  rm -f "$VENV/static/.done"  # the package map may have changed with pyproject.toml
fi
# Static tools (pyright, pylint, an IDE) follow a plain path in a .pth file, not the import hook
# by which the editable install maps hapticproxy.* onto the top-level folders. So .venv/static/
# holds hapticproxy/<name> -> <folder> links, one per top-level entry of pyproject.toml's
# package-dir table (links to folders: a new module is seen at once), and a .pth names it;
# Python imports the same files through it.
if [ ! -f "$VENV/static/.done" ]; then
  "$VENV/bin/python" - "$ROOT" "$VENV/static" <<'PY' || { echo "run.sh: linking .venv/static/ failed" >&2; exit 1; }
import os, sys, sysconfig, tomllib
root, tree = sys.argv[1], sys.argv[2]
with open(os.path.join(root, "pyproject.toml"), "rb") as fh:
    dirs = tomllib.load(fh)["tool"]["setuptools"]["package-dir"]
os.makedirs(os.path.join(tree, "hapticproxy"), exist_ok=True)
for name, folder in dirs.items():
    parent, _, last = name.rpartition(".")
    if parent != "hapticproxy":  # a sub-package must be its parent's sub-folder, as the links show it
        assert folder == dirs[parent] + "/" + last, f"{name} = {folder} is not a sub-folder of {dirs[parent]}"
        continue
    link = os.path.join(tree, "hapticproxy", last)
    if os.path.lexists(link):
        os.remove(link)
    os.symlink(os.path.join(root, folder), link)
with open(os.path.join(sysconfig.get_paths()["purelib"], "hapticproxy-static.pth"), "w") as fh:
    fh.write(tree + "\n")
open(os.path.join(tree, ".done"), "w").close()
PY
fi
# Compile every kernel now (or load it from numba's cache): nothing may compile once the haptic
# loop has armed its deadlines. Quiet when everything is cached already.
"$VENV/bin/hapticproxy" warmup --quiet || { echo "run.sh: compiling the kernels failed" >&2; exit 1; }

job=${1:-demo}
[ $# -gt 0 ] && shift
case "$job" in
  test)
    # pytest exits 5 when no test ran; that is a failure too.
    exec "$VENV/bin/python" -m pytest "$@" ;;
  *)
    exec "$VENV/bin/hapticproxy" "$job" "$@" ;;
esac

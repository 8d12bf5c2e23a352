#!/usr/bin/env bash
# Create or update the stock-Jazzy test venv; `make venv-stock` calls it under a lock.
#   usage: tools/make_stock_venv.sh PYTHON VENV STAMP INSTALLER
# PYTHON     python3.12 (the Python of Ubuntu 24.04, where ROS 2 Jazzy installs)
# VENV       the venv directory (.venv-stock; never the main .venv)
# STAMP      file to create on success; its name carries the key of requirements-stock.txt
# INSTALLER  uv (pip installs uv into the venv first; pip is used if that fails) or pip
# The packages are those of requirements-stock.txt: numpy 1.26, scipy 1.11 and the library's
# pure-Python needs, no ROS and no numba (the library must run without them).
set -euo pipefail
python="$1" venv="$2" stamp="$3" installer="$4"
reqs=requirements-stock.txt

[ -f "$stamp" ] && exit 0

# A pyenv shim answers to python3.12 even where 3.12 is not the selected version: ask pyenv.
if ! "$python" -c '' 2>/dev/null; then
  wanted="$(basename "$python" | sed 's/^python//')"
  found="$(pyenv root 2>/dev/null)/versions/$(pyenv versions --bare 2>/dev/null \
           | grep -x "${wanted//./\\.}\(\.[0-9]*\)\?" | tail -n 1)/bin/python$wanted"
  if [ -x "$found" ] && "$found" -c '' 2>/dev/null; then
    python="$found"
  else
    echo "venv-stock: no $python here: install Python $wanted (apt-get install python$wanted-venv)" \
         "or pass PYTHON_STOCK=/path/to/python$wanted" >&2
    exit 1
  fi
fi

echo "== venv-stock: installing $reqs into $venv ($(basename "$stamp"))"
# shellcheck source=tools/venv_common.sh
source tools/venv_common.sh
fresh_venv
uv_pin="$(grep -i '^uv==' constraints-jazzy.txt || echo uv)"
if [ "$installer" = uv ] && install_uv "$uv_pin"; then
  echo "   installer: uv $("$venv/bin/uv" --version | cut -d' ' -f2)"
  # hard links into uv's cache: nothing here writes through them (compiling adds new files)
  UV_PYTHON_DOWNLOADS=never UV_NO_PROGRESS=1 UV_LINK_MODE=hardlink \
    "$venv/bin/uv" pip install -q --compile-bytecode --python "$vpy" -r "$reqs"
else
  echo "   installer: pip"
  venv_pip install -q --disable-pip-version-check -r "$reqs"
fi
"$vpy" - <<'PY'
import importlib.util
import sys
for absent in ('rclpy', 'numba'):
    if importlib.util.find_spec(absent) is not None:
        sys.exit(f'venv-stock: {absent} is installed, but this environment must run without it')
PY
touch "$stamp"
echo "== venv-stock: ready"

# Shared by tools/make_venv.sh and tools/make_stock_venv.sh, sourced once $python and $venv are
# set: the venv made for this directory without pip, its pip on demand, uv installed into it.

# Create the venv (again where it was made for another directory, or an earlier attempt died
# before writing .origin: it is not relocatable, its shebangs and patched paths are absolute),
# without ensurepip's pip (8 s, most of it byte-compiling pip); drop its old stamps.
fresh_venv() {
  local here
  here="$(pwd -P)"
  if [ -d "$venv" ] && [ "$(cat "$venv/.origin" 2>/dev/null)" != "$here" ]; then
    echo "   $venv was made elsewhere (or is incomplete): recreating it"
    rm -rf "$venv"
  fi
  if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv --without-pip "$venv"
    echo "$here" > "$venv/.origin"
  fi
  rm -f "$venv"/.stamp-*
  vpy="$venv/bin/python"
}

# The venv's own pip, from ensurepip where it has none.
venv_pip() {
  "$vpy" -m pip --version > /dev/null 2>&1 || "$vpy" -m ensurepip > /dev/null
  "$vpy" -m pip "$@"
}

# Install uv (ARGS: its pin, as pip takes it) into the venv: by the system Python's pip (22.3
# and later install into another environment with --python), else by the venv's own. Fails
# where neither can: the caller then installs with pip.
install_uv() {
  "$python" -m pip --python "$vpy" install -q --disable-pip-version-check "$@" \
    > /dev/null 2>&1 || venv_pip install -q --disable-pip-version-check "$@" 2> /dev/null
}

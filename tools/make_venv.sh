#!/usr/bin/env bash
# Create or update the venv from the pins; `make venv` calls it under a lock.
#   usage: tools/make_venv.sh PYTHON VENV STAMP INSTALLER
# PYTHON     python3.11 to create the venv with
# VENV       the venv directory (.venv)
# STAMP      file to create on success; its name carries the key of the pins' content
# INSTALLER  uv (pip installs uv into the venv first; pip is used if that fails) or pip
set -euo pipefail
python="$1" venv="$2" stamp="$3" installer="$4"
reqs=requirements-jazzy.in cons=constraints-jazzy.txt patch=tools/patch_cmake_exports.py

# Another make may have finished the same venv while this one waited for the lock.
[ -f "$stamp" ] && exit 0

echo "== venv: installing the pinned wheels into $venv ($(basename "$stamp"))"
# shellcheck source=tools/venv_common.sh
source tools/venv_common.sh
fresh_venv
if [ "$installer" = uv ] && install_uv -c "$cons" uv; then
  echo "   installer: uv $("$venv/bin/uv" --version | cut -d' ' -f2)"
  # hard links into uv's cache (7 s where copies took 20 s): the CMake-export patch writes a
  # new file over each one it changes (tools/patch_cmake_exports.py), never through a link,
  # so the cache stays as uv made it; uv copies where the cache is on another file system
  UV_PYTHON_DOWNLOADS=never UV_NO_PROGRESS=1 UV_LINK_MODE=hardlink \
    "$venv/bin/uv" pip install -q --python "$vpy" -r "$reqs" -c "$cons" pip
  # uv writes no .pyc, and without them every start of ./rotor-id compiles numpy, scipy and
  # rosbags from source again when the environment sets PYTHONDONTWRITEBYTECODE (0.8 s
  # instead of 0.3 s for `rotor-id identify`): byte-compile site-packages on both cores, but
  # not the packages that no run imports or one test imports once (pandas and statsmodels:
  # test_filter_error's reference likelihood), 40 % of its files (about 15 s of a CI run), nor
  # the packages' own test suites (tests/, test/: a third of the files left, 9 s of CPU).
  "$vpy" -m compileall -q -j 0 \
    -x '/(pandas|statsmodels|pip|mypyc|narwhals|formulaic|snowballstemmer|coverage|tests?)/' \
    "$("$vpy" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" > /dev/null \
    || echo "   some files of site-packages did not byte-compile (they compile when imported)"
else
  echo "   installer: pip"
  venv_pip install -q --disable-pip-version-check -r "$reqs" -c "$cons"
fi
"$vpy" "$patch" --quiet
"$vpy" "$patch" --check --quiet
touch "$stamp"
echo "== venv: ready"

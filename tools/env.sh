# shellcheck shell=bash
# Workspace environment of this repository, for bash. Source it, don't run it:
#
#   . tools/env.sh              # venv + built workspace (needs `make build` first)
#   . tools/env.sh --venv-only  # venv only: what `colcon build` needs
#
# Sets what install/local_setup.sh sets plus the venv:
#   PATH, VIRTUAL_ENV       .venv/bin first, so `python`, `colcon`, `pytest` are the venv's
#   AMENT_PREFIX_PATH       install/rotor_id, install/rotor_id_msgs, then .venv (the ros-* wheels)
#   CMAKE_PREFIX_PATH       .venv (find_package(ament_cmake) etc. at build time)
#   PYTHONPATH              the source tree first (edits apply without a rebuild), then
#                           install/*/lib/python3.11/site-packages (rotor_id_msgs, egg-info)
#   LD_LIBRARY_PATH         install/rotor_id_msgs/lib (typesupport libraries of our messages)
#   ROS_LOG_DIR             only if HOME is unset (rcl logging needs one of them)
# The ROS variables are reset first, so a sourced /opt/ros/<distro> cannot leak in.
# Returns 1, with one line on stderr, if the venv (or, without --venv-only, the install
# tree) is missing.

_rid_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
_rid_venv="$_rid_root/.venv"
if [ ! -x "$_rid_venv/bin/python" ] || \
   { [ "${1:-}" != "--venv-only" ] && [ ! -f "$_rid_root/install/local_setup.sh" ]; }; then
  echo "rotor_id: no built environment in $_rid_root (.venv or install/ missing): run 'make test' or 'make demo' there first" >&2
  unset _rid_root _rid_venv
  return 1
fi

export VIRTUAL_ENV="$_rid_venv"
case ":${PATH:-}:" in
  *":$_rid_venv/bin:"*) ;;
  *) export PATH="$_rid_venv/bin${PATH:+:$PATH}" ;;
esac
unset COLCON_PREFIX_PATH PYTHONPATH PYTHONHOME
export AMENT_PREFIX_PATH="$_rid_venv"
export CMAKE_PREFIX_PATH="$_rid_venv"

if [ "${1:-}" != "--venv-only" ]; then
  # colcon's local_setup.sh is not `set -u` safe; COLCON_CURRENT_PREFIX makes it work even if
  # the tree was moved after the build.
  case "$-" in *u*) _rid_nounset=1; set +u ;; *) _rid_nounset= ;; esac
  export COLCON_CURRENT_PREFIX="$_rid_root/install"
  # local_setup.sh asks Python for its commands, a tenth of a second that every `rotor-id`
  # paid. They depend on the install tree alone: kept beside it (install/.setup_commands.sh)
  # until a build rewrites local_setup.sh or a package's hooks, and used where they are plain
  # exports (else local_setup.sh runs as it is).
  _rid_commands="$_rid_root/install/.setup_commands.sh"
  _rid_fresh=1
  for _rid_f in "$_rid_root/install/local_setup.sh" "$_rid_root"/install/*/share/*/package.dsv; do
    [ "$_rid_commands" -nt "$_rid_f" ] || _rid_fresh=
  done
  # (made for this tree where it is now: a copied tree has copied paths in them)
  _rid_f=
  [ -n "$_rid_fresh" ] && read -r _rid_f < "$_rid_commands"
  [ "$_rid_f" = "# $_rid_root" ] || _rid_fresh=
  if [ -z "$_rid_fresh" ]; then
    # made where the variables hold nothing yet: colcon leaves out a path already there
    if env -u LD_LIBRARY_PATH -u PYTHONPATH -u AMENT_PREFIX_PATH -u CMAKE_PREFIX_PATH \
        "$_rid_venv/bin/python" "$_rid_root/install/_local_setup_util_sh.py" sh \
        > "$_rid_commands.$$" 2>/dev/null && ! grep -qv '^export ' "$_rid_commands.$$"; then
      { printf '# %s\n' "$_rid_root"; cat "$_rid_commands.$$"; } > "$_rid_commands.$$.kept" \
        && mv -f "$_rid_commands.$$.kept" "$_rid_commands" && _rid_fresh=1
      rm -f "$_rid_commands.$$"
    else
      rm -f "$_rid_commands.$$"
    fi
  fi
  if [ -n "$_rid_fresh" ]; then
    # shellcheck disable=SC1090
    . "$_rid_commands"
    export COLCON_PREFIX_PATH="$_rid_root/install"      # what local_setup.sh adds itself
  else
    # shellcheck disable=SC1091
    . "$_rid_root/install/local_setup.sh"
  fi
  unset COLCON_CURRENT_PREFIX _rid_commands _rid_fresh _rid_f
  [ -n "$_rid_nounset" ] && set -u
  unset _rid_nounset
  export PYTHONPATH="$_rid_root${PYTHONPATH:+:$PYTHONPATH}"
  # local_setup.sh leaves a trailing ':' (= current directory) when LD_LIBRARY_PATH was empty.
  LD_LIBRARY_PATH="$(printf '%s' "${LD_LIBRARY_PATH:-}" | tr -s ':' | sed 's/^://; s/:$//')"
  export LD_LIBRARY_PATH
fi

if [ -z "${HOME:-}" ] && [ -z "${ROS_LOG_DIR:-}" ] && [ -z "${ROS_HOME:-}" ]; then
  export ROS_LOG_DIR="$_rid_root/log/ros"
fi
unset _rid_root _rid_venv
return 0

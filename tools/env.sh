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
  # shellcheck disable=SC1091
  . "$_rid_root/install/local_setup.sh"
  unset COLCON_CURRENT_PREFIX
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

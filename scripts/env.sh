# Source this for a shell (or a script) inside the built workspace: venv + install/.
_afm_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
# shellcheck disable=SC1091
source "$_afm_root/.venv/bin/activate"
export AMENT_PREFIX_PATH="$_afm_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export CMAKE_PREFIX_PATH="$_afm_root/.venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
# colcon's setup script reads unset variables; relax nounset around it.
_afm_had_u=$([[ $- == *u* ]] && echo 1 || true)
set +u
# shellcheck disable=SC1091
source "$_afm_root/install/setup.bash"
[ -n "$_afm_had_u" ] && set -u
# One machine, no network: keep DDS discovery on loopback unless the user chose otherwise.
export ROS_AUTOMATIC_DISCOVERY_RANGE=${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}
unset _afm_root _afm_had_u

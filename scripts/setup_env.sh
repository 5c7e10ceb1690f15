# Source this file (bash) to run vlp_ros from this checkout:
#   source scripts/setup_env.sh
# It activates the project's virtualenv with the ROS 2 wheels (if present),
# overlays the colcon install space and sets the DDS environment vlp_ros needs.
_vlp_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"

if [ -x "$_vlp_root/.venv/bin/python" ]; then
  # shellcheck disable=SC1091
  source "$_vlp_root/.venv/bin/activate"
  # The wheels install their ament index into the venv prefix.
  export AMENT_PREFIX_PATH="$_vlp_root/.venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
fi
if [ -f "$_vlp_root/install/setup.bash" ]; then
  # shellcheck disable=SC1091
  source "$_vlp_root/install/setup.bash"
fi

export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# Fast DDS's default transports silently drop best-effort messages larger than
# about 512 KB (every camera image); LARGE_DATA uses TCP + shared memory for them.
export FASTDDS_BUILTIN_TRANSPORTS="${FASTDDS_BUILTIN_TRANSPORTS:-LARGE_DATA}"
unset _vlp_root

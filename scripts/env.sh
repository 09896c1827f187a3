# Environment for protocad-ros; sourced by scripts/protocad and by .venv/bin/activate.
# ROS 2 from PyPI wheels: the ament index lives in the venv prefix.
_protocad_prefix="${VIRTUAL_ENV:-$(cd "$(dirname "${BASH_SOURCE[0]}")/../.venv" && pwd)}"
case ":${AMENT_PREFIX_PATH:-}:" in
  *":$_protocad_prefix:"*) ;;
  *) export AMENT_PREFIX_PATH="$_protocad_prefix${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;;
esac
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# DDS discovery must never leave this machine (default discovery multicasts on every
# interface). A per-user domain id keeps concurrent users apart; tests pick their own.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$(( $(id -u) % 100 + 1 ))}"
# Participants announce themselves every 0.5 s instead of 3 s, so a new one (a `ros2` verb, a
# node) finds the running ones within ~0.6 s instead of up to ~3 s; a profile of your own wins.
export FASTRTPS_DEFAULT_PROFILES_FILE="${FASTRTPS_DEFAULT_PROFILES_FILE:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/sim_bridge/fastdds_discovery.xml}"
# A fleet discovers through a Fast DDS Discovery Server instead (export ROS_DISCOVERY_SERVER=
# HOST:PORT before sourcing this; the launchers take --discovery-server). A shell's tools
# (ros2 topic/node list, by hand) must then be super clients, or they see only their own topics;
# the launchers start their nodes as plain clients whatever this says.
if [ -n "${ROS_DISCOVERY_SERVER:-}" ]; then export ROS_SUPER_CLIENT="${ROS_SUPER_CLIENT:-TRUE}"; fi
# Headless rendering: EGL with Mesa (osmesa also works: MUJOCO_GL=osmesa).
export MUJOCO_GL="${MUJOCO_GL:-egl}"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-$MUJOCO_GL}"
export PYTHONUNBUFFERED=1
unset _protocad_prefix

# Source this file to get the suite's environment in a shell:  source scripts/env.sh
# It activates .venv, puts the ROS 2 Jazzy wheels (or a sourced /opt/ros/jazzy) on the
# library and ament paths, sources the colcon workspace, and sets the DDS profile
# (SLAM_DDS_PROFILE: loopback by default, or lan; see below).
# Option --no-workspace skips ros2_ws/install (used by the bootstrap before the first build).

_slam_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
_slam_venv="$_slam_root/.venv"
_slam_nounset=0; [[ $- == *u* ]] && _slam_nounset=1; set +u

if [[ ! -x "$_slam_venv/bin/python" ]]; then
  echo "scripts/env.sh: .venv is missing; run scripts/bootstrap.sh first" >&2
else
  export VIRTUAL_ENV="$_slam_venv"
  case ":$PATH:" in *":$_slam_venv/bin:"*) ;; *) export PATH="$_slam_venv/bin:$PATH" ;; esac
  if grep -q '^slam-mode = wheels$' "$_slam_venv/pyvenv.cfg"; then
    _slam_site="$_slam_venv/lib/python3.11/site-packages"
    _slam_libs="$_slam_venv/lib"
    for _d in "$_slam_site"/ros_*.libs; do [[ -d "$_d" ]] && _slam_libs="$_slam_libs:$_d"; done
    case ":${LD_LIBRARY_PATH:-}:" in *":$_slam_venv/lib:"*) ;; *)
      export LD_LIBRARY_PATH="$_slam_libs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" ;; esac
    case ":${AMENT_PREFIX_PATH:-}:" in *":$_slam_venv:"*) ;; *)
      export AMENT_PREFIX_PATH="$_slam_venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;; esac
    case ":${CMAKE_PREFIX_PATH:-}:" in *":$_slam_venv:"*) ;; *)
      export CMAKE_PREFIX_PATH="$_slam_venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}" ;; esac
    # The wheels re-exec every Python process to set LD_LIBRARY_PATH; it is set already.
    export _ROS_WHEELS_BOOTSTRAP_COMPLETE=1
    export ROS_DISTRO=jazzy ROS_VERSION=2 ROS_PYTHON_VERSION=3
    unset _d _slam_site _slam_libs
  fi
  if [[ "${1:-}" != "--no-workspace" ]]; then
    if [[ -f "$_slam_root/ros2_ws/install/setup.bash" ]]; then
      # shellcheck disable=SC1091
      source "$_slam_root/ros2_ws/install/setup.bash"
      # No `ros2 run` without the ROS CLI: put the packages' executables on PATH instead.
      for _d in "$_slam_root"/ros2_ws/install/*/lib/*/; do
        [[ "$_d" == */python3.*/ ]] && continue
        case ":$PATH:" in *":${_d%/}:"*) ;; *) PATH="${_d%/}:$PATH" ;; esac
      done
      export PATH; unset _d
    else
      echo "scripts/env.sh: ros2_ws is not built; run scripts/bootstrap.sh" >&2
    fi
  fi
  export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
  # DDS profile, one setting: SLAM_DDS_PROFILE=loopback (the default: tests and demos stay on
  # this machine, localhost discovery, UDPv4 on 127.0.0.1 only) or lan (a robot and a laptop:
  # discovery over the subnet, UDPv4 on every interface). Both add shared memory.
  case "${SLAM_DDS_PROFILE:-loopback}" in
    loopback) _slam_range=LOCALHOST ;;
    lan) _slam_range=SUBNET ;;
    *) _slam_range=""
       echo "scripts/env.sh: SLAM_DDS_PROFILE='${SLAM_DDS_PROFILE}' is not loopback or lan;" \
            "no DDS profile set" >&2 ;;
  esac
  if [[ -n "$_slam_range" ]]; then
    export SLAM_DDS_PROFILE="${SLAM_DDS_PROFILE:-loopback}"
    export ROS_AUTOMATIC_DISCOVERY_RANGE="$_slam_range"
    export FASTRTPS_DEFAULT_PROFILES_FILE="$_slam_root/src/slam_bringup/config/fastdds_$SLAM_DDS_PROFILE.xml"
    export FASTDDS_DEFAULT_PROFILES_FILE="$FASTRTPS_DEFAULT_PROFILES_FILE"
  fi
  unset _slam_range
  export SLAM_REPO_ROOT="$_slam_root"
fi
[[ $_slam_nounset == 1 ]] && set -u
unset _slam_root _slam_venv _slam_nounset

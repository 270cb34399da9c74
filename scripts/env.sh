# shellcheck shell=bash
# Source this file (`source scripts/env.sh`) to use rclpy from .venv/ and the pwm_actuator_msgs
# package built in .ros-ws/ by scripts/setup.sh: it puts the venv's python, colcon and cmake first
# on PATH and makes the messages importable and loadable. It changes only environment variables
# of the current shell; sourcing it twice adds nothing twice. It does not build anything: run
# scripts/setup.sh first.
#
# PWM_DISTRO picks the ROS 2 distribution: jazzy (the default: .venv/ and .ros-ws/) or kilted
# (.venv-kilted/ and .ros-ws-kilted/, from `scripts/setup.sh --distro kilted`), e.g.
# `PWM_DISTRO=kilted source scripts/env.sh`. Use one distribution per shell: sourcing both
# would put both on the paths.

_pwm_env_src="${BASH_SOURCE[0]:-$0}"
PWM_ACTUATOR_ROOT="$(cd "$(dirname "$_pwm_env_src")/.." && pwd)"
export PWM_ACTUATOR_ROOT
unset _pwm_env_src

_pwm_prepend() {
    # _pwm_prepend VAR DIR: put DIR first in the colon-separated VAR unless it is there already.
    local _cur
    eval "_cur=\${$1:-}"
    case ":$_cur:" in
        *":$2:"*) ;;
        *) if [ -n "$_cur" ]; then export "$1=$2:$_cur"; else export "$1=$2"; fi ;;
    esac
}

_pwm_distro="${PWM_DISTRO:-jazzy}"
case "$_pwm_distro" in
    jazzy) _pwm_suffix="" _pwm_setup="scripts/setup.sh" ;;
    kilted) _pwm_suffix="-kilted" _pwm_setup="scripts/setup.sh --distro kilted" ;;
    *)
        echo "env.sh: unknown PWM_DISTRO '$_pwm_distro' (jazzy or kilted); using jazzy" >&2
        _pwm_distro=jazzy _pwm_suffix="" _pwm_setup="scripts/setup.sh"
        ;;
esac
_pwm_venv="$PWM_ACTUATOR_ROOT/.venv$_pwm_suffix"
_pwm_msgs="$PWM_ACTUATOR_ROOT/.ros-ws$_pwm_suffix/install/pwm_actuator_msgs"

if [ ! -x "$_pwm_venv/bin/python" ] || [ ! -d "$_pwm_msgs" ]; then
    echo "env.sh: $PWM_ACTUATOR_ROOT is not set up yet for $_pwm_distro; run $_pwm_setup" >&2
fi

export VIRTUAL_ENV="$_pwm_venv"
_pwm_prepend PATH "$_pwm_venv/bin"
# The venv first, then the messages in front of it, as a colcon overlay would order them.
_pwm_prepend AMENT_PREFIX_PATH "$_pwm_venv"
_pwm_prepend AMENT_PREFIX_PATH "$_pwm_msgs"
_pwm_prepend CMAKE_PREFIX_PATH "$_pwm_venv"
_pwm_prepend CMAKE_PREFIX_PATH "$_pwm_msgs"
_pwm_prepend PYTHONPATH "$_pwm_msgs/lib/python3.11/site-packages"
# The venv's python also adds its ROS libraries itself (the wheels' bootstrapper re-executes it
# once with them on LD_LIBRARY_PATH); they are listed here for other programs, and the
# messages' own libraries, which the bootstrapper does not know, for everyone.
_pwm_prepend LD_LIBRARY_PATH "$_pwm_venv/lib"
_pwm_prepend LD_LIBRARY_PATH "$_pwm_msgs/lib"
# Fast DDS is the only RMW published as wheels; a value from a system ROS install would not load.
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
export ROS_VERSION=2
export ROS_DISTRO="$_pwm_distro"
export ROS_PYTHON_VERSION=3

unset _pwm_venv _pwm_msgs _pwm_distro _pwm_suffix _pwm_setup
unset -f _pwm_prepend

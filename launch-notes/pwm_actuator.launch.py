"""ROS 2 launch file for pwm_actuator_node (heater on pw01, valve on pw02, see
pwm_actuator.params.yaml next to this file).

    ros2 launch pwm_actuator.launch.py
    ros2 launch pwm_actuator.launch.py binary:=$HOME/pwm_actuator/target/release/pwm_actuator_node \
        namespace:=/boiler rt_priority:=40 params_file:=/etc/pwm_actuator/pwm_actuator.params.yaml

The node is a standalone Rust binary, not a colcon-built C++ or Python package, so `ros2 launch`
cannot find it by package name on its own. Two ways to start it:

1. ExecuteProcess with the binary's path (the working default below, `binary` launch argument).
   The node's own options come first, then `--ros-args` with the standard ROS arguments, exactly
   as on a shell command line.
2. launch_ros.actions.Node (commented out below): install the binary into an ament package's
   lib directory, `<prefix>/lib/pwm_actuator/pwm_actuator_node`, with the package registered in
   the ament index (an ament_cmake package whose CMakeLists.txt does
   `install(PROGRAMS pwm_actuator_node DESTINATION lib/${PROJECT_NAME})`). launch_ros then adds
   `--ros-args -r __node:=... -r __ns:=... --params-file ... -r from:=to` itself.

Both variants pass the same arguments. The node stops on SIGINT (Ctrl-C in `ros2 launch`) and
on SIGTERM alike: it drives every output inactive and exits 0.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, ThisLaunchFileDir

# from launch_ros.actions import Node


def generate_launch_description():
    binary = LaunchConfiguration("binary")
    node_name = LaunchConfiguration("node_name")
    namespace = LaunchConfiguration("namespace")
    params_file = LaunchConfiguration("params_file")
    rt_priority = LaunchConfiguration("rt_priority")

    args = [
        DeclareLaunchArgument(
            "binary",
            default_value="/usr/local/bin/pwm_actuator_node",
            description="Path of pwm_actuator_node (cargo build --release --bins; "
            "target/release/pwm_actuator_node).",
        ),
        DeclareLaunchArgument(
            "node_name", default_value="pwm_actuator", description="Node name (__node)."
        ),
        DeclareLaunchArgument(
            "namespace",
            default_value="/boiler",
            description="Node namespace (__ns), absolute: starts with '/'.",
        ),
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([ThisLaunchFileDir(), "pwm_actuator.params.yaml"]),
            description="ROS 2 parameter file.",
        ),
        DeclareLaunchArgument(
            "rt_priority",
            default_value="0",
            description="SCHED_FIFO priority of the output thread, 1..99; 0 = normal "
            "scheduling. Needs an rtprio limit or CAP_SYS_NICE (see docs/realtime.md); "
            "when refused the node logs one warning and runs normally.",
        ),
    ]

    # Where the channels' commands come from: the controllers' topics are mapped onto the node's
    # ~/<ch>/duty inputs. Relative targets resolve in the node's namespace
    # (heater/power -> /boiler/heater/power).
    remaps = [
        ("~/pw01/duty", "heater/power"),
        ("~/pw02/duty", "valve/opening"),
    ]

    # Variant 1 (default): the binary by path.
    cmd = [binary, "--rt-priority", rt_priority, "--ros-args"]
    cmd += ["-r", ["__node:=", node_name], "-r", ["__ns:=", namespace]]
    cmd += ["--params-file", params_file]
    for src, dst in remaps:
        cmd += ["-r", f"{src}:={dst}"]
    node = ExecuteProcess(
        cmd=cmd,
        name=node_name,
        output="screen",
        # Time the node has to drive its outputs off after SIGINT before launch sends SIGTERM;
        # it needs well under a second.
        sigterm_timeout="5",
        sigkill_timeout="5",
    )

    # Variant 2: the binary installed as <prefix>/lib/pwm_actuator/pwm_actuator_node of an
    # ament package named pwm_actuator. Replace `node` above with this.
    # node = Node(
    #     package="pwm_actuator",
    #     executable="pwm_actuator_node",
    #     name=node_name,
    #     namespace=namespace,
    #     parameters=[params_file],
    #     remappings=remaps,
    #     arguments=["--rt-priority", rt_priority],  # the node's own options, before --ros-args
    #     output="screen",
    #     sigterm_timeout="5",
    #     sigkill_timeout="5",
    # )

    return LaunchDescription(args + [node])

"""ROS 2 launch file for pwm_actuator_node as a managed (lifecycle) node: launch_ros'
LifecycleNode starts it with --managed, then configures it and, once configure has brought it
to inactive, activates it. Its lines are requested on configure and follow their channels only
while it is active.

    ros2 launch pwm_actuator_managed.launch.py
    ros2 launch pwm_actuator_managed.launch.py binary:=$HOME/pwm_actuator/target/release/pwm_actuator_node \
        namespace:=/boiler params_file:=/etc/pwm_actuator/pwm_actuator.params.yaml

launch_ros runs an executable given by path when no package is named, so the binary need not
be installed in an ament package. LifecycleNode watches ~/transition_event and calls
~/change_state, both of which the node provides with --managed. Drop the two event handlers to
leave the transitions to a supervisor (nav2's lifecycle manager, `ros2 lifecycle set`).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.events import matches_action
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, ThisLaunchFileDir
from launch_ros.actions import LifecycleNode
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition


def generate_launch_description():
    binary = LaunchConfiguration("binary")
    args = [
        DeclareLaunchArgument(
            "binary",
            default_value="/usr/local/bin/pwm_actuator_node",
            description="Path of pwm_actuator_node.",
        ),
        DeclareLaunchArgument("node_name", default_value="pwm_actuator"),
        DeclareLaunchArgument("namespace", default_value="/boiler"),
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([ThisLaunchFileDir(), "pwm_actuator.params.yaml"]),
        ),
    ]
    node = LifecycleNode(
        executable=binary,
        name=LaunchConfiguration("node_name"),
        namespace=LaunchConfiguration("namespace"),
        # The node's own options come before --ros-args, which launch_ros adds.
        arguments=["--managed"],
        parameters=[LaunchConfiguration("params_file")],
        remappings=[("~/pw01/duty", "heater/power"), ("~/pw02/duty", "valve/opening")],
        output="screen",
    )
    configure = EmitEvent(
        event=ChangeState(
            lifecycle_node_matcher=matches_action(node),
            transition_id=Transition.TRANSITION_CONFIGURE,
        )
    )
    activate_when_inactive = RegisterEventHandler(
        OnStateTransition(
            target_lifecycle_node=node,
            # Only after configure: a later deactivate (active -> inactive) is left alone.
            start_state="configuring",
            goal_state="inactive",
            entities=[
                EmitEvent(
                    event=ChangeState(
                        lifecycle_node_matcher=matches_action(node),
                        transition_id=Transition.TRANSITION_ACTIVATE,
                    )
                )
            ],
        )
    )
    return LaunchDescription(args + [node, activate_when_inactive, configure])

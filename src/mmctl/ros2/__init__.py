"""The ROS 2 bridge (the ``mmctl[ros2]`` extra): the daemon seen from ROS 2.

:mod:`.messages` holds the ROS 2 message types as DDS types (cyclonedds' IDL classes,
named as ROS 2's ``rmw`` names them), :mod:`.bridge` publishes a telemetry row on them,
and :mod:`.process` runs the bridge in a child process that maps the loop's sample ring
(as the telemetry child does): it never runs on the loop, nor takes its interpreter.
"""

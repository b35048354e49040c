"""Robotics outputs of the fusion centre (docs/robotics.md): the record -> message mapping
(:mod:`.topics`), MCAP files and Foxglove messages (:mod:`.mcap_out`), the live Foxglove server
(:mod:`.foxglove_live`), ROS 2 bags (:mod:`.ros2_bag`) and the run's set of them
(:mod:`.outputs`). Importing this package loads none of the SDKs; the modules load theirs.
"""

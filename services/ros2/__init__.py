"""ROS 2 over Zenoh without ROS: rmw_zenoh's wire format (:mod:`.wire`), CDR messages through
``rosbags`` (:mod:`.codec`) and the bridge service ``confnav serve ros2`` (:mod:`.bridge`)."""

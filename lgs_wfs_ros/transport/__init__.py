"""Frame transports between the nodes of one host.

``ros``: frames are ``sensor_msgs/Image`` messages on the ``frame`` topic (rclpy + Fast DDS:
each 1.84 MB full-pupil frame is copied ~4 times). ``shm``: frames go through iceoryx2
shared memory (:mod:`.shm`): rendered or decoded straight into a loaned buffer, read in place
by the subscriber; stamps, sequence numbers and the sensor's id travel in a fixed header.
Slopes, truths, descriptions and parameters stay ROS topics either way.
"""

from .shm import (AVAILABLE, FrameHeader, ShmFrame, ShmFramePublisher, ShmFrameSubscriber,
                  ShmUnavailable, default_transport, sensor_id, service_name)

TRANSPORTS = ("ros", "shm")

__all__ = ["AVAILABLE", "FrameHeader", "ShmFrame", "ShmFramePublisher", "ShmFrameSubscriber",
           "ShmUnavailable", "TRANSPORTS", "default_transport", "sensor_id", "service_name"]

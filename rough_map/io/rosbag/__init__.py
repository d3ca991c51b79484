"""ROS bags without ROS: inspect them and import a traverse from them.

Reads ROS 1 ``.bag`` files and ROS 2 bags (a folder with ``metadata.yaml``, or a single
``.db3``/``.mcap`` file) through :class:`rosbags.highlevel.AnyReader`. Messages used:

* ``sensor_msgs/PointCloud2``: any field layout and endianness, see :func:`pointcloud2_to_xyz`;
* ``nav_msgs/Odometry``: the pose of the vehicle (``child_frame_id``) in the world
  (``header.frame_id``);
* ``sensor_msgs/Imu``: attitude from the orientation quaternion;
* ``tf2_msgs/TFMessage`` on ``/tf_static``: the mounting of the sensor on the vehicle.

Times are the message header stamps (the bag's receive time where a stamp is zero).
Angles follow :mod:`rough_map.types`: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

The same messages can be written (:func:`write_bag`, :func:`pointcloud2_message`...), and
:func:`write_example_bag` records a traverse (a simulated one, say) as a rover's logger
would: the example bag of the README and the bags of the tests are made this way.

Damaged or hostile bags give a one-line :class:`~rough_map.errors.FileFormatError`: the
record sizes of ``.bag`` and ``.mcap`` files and the fields of ``metadata.yaml`` are checked
against the files before rosbags reads them (:mod:`~.checks`), and the standard message
types a bag defines must have the standard fields.

Modules: :mod:`~.reader` (opening bags, topics), :mod:`~.messages` (decoding messages),
:mod:`~.tf` (the tf tree), :mod:`~.trajectory` (odometry and IMU over time),
:mod:`~.importer` (:func:`import_bag`), :mod:`~.writer` (building and writing messages),
:mod:`~.example` (:func:`write_example_bag`).
"""

from rough_map.io.rosbag.example import EXAMPLE_LIDAR_MOUNT, EXAMPLE_T0_NS, write_example_bag
from rough_map.io.rosbag.importer import import_bag
from rough_map.io.rosbag.messages import (
    IMU,
    ODOMETRY,
    POINTCLOUD2,
    TF_MESSAGE,
    TF_STATIC_TOPIC,
    OdometryPose,
    imu_rpy,
    odometry_pose,
    pointcloud2_to_xyz,
    stamp_ns,
)
from rough_map.io.rosbag.reader import BagInfo, TopicInfo, inspect_bag, open_bag
from rough_map.io.rosbag.tf import Transform, read_transforms, static_transform, tf_transforms
from rough_map.io.rosbag.trajectory import Trajectory, read_imu, read_odometry
from rough_map.io.rosbag.writer import (
    BAG_STORAGES,
    PointCloud2Layout,
    header_message,
    imu_message,
    odometry_message,
    pointcloud2_message,
    ros_typestore,
    tf_message,
    write_bag,
)

__all__ = [
    "BAG_STORAGES",
    "EXAMPLE_LIDAR_MOUNT",
    "EXAMPLE_T0_NS",
    "IMU",
    "ODOMETRY",
    "POINTCLOUD2",
    "TF_MESSAGE",
    "TF_STATIC_TOPIC",
    "BagInfo",
    "OdometryPose",
    "PointCloud2Layout",
    "TopicInfo",
    "Trajectory",
    "Transform",
    "header_message",
    "import_bag",
    "imu_message",
    "imu_rpy",
    "inspect_bag",
    "odometry_message",
    "odometry_pose",
    "open_bag",
    "pointcloud2_message",
    "pointcloud2_to_xyz",
    "read_imu",
    "read_odometry",
    "read_transforms",
    "ros_typestore",
    "stamp_ns",
    "static_transform",
    "tf_message",
    "tf_transforms",
    "write_bag",
    "write_example_bag",
]

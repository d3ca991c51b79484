"""Readers and writers: point clouds, ROS bags, traverse folders and other files.

One module per source:

* :mod:`~rough_map.io.pointcloud`: point clouds by file suffix (``read_cloud``,
  ``write_cloud``), KITTI scans and poses;
* :mod:`~rough_map.io.las`: LAS/LAZ with classification and coordinate reference system;
* :mod:`~rough_map.io.rosbag`: ROS 1 and ROS 2 bags (inspect, import a traverse, write);
* :mod:`~rough_map.io.traverse`: traverse folders (``traverse.json`` and its files);
* :mod:`~rough_map.io.model_files`: where a terrain model's files are, and its card (read
  without scikit-learn; :mod:`rough_map.classify.persistence` loads the model itself).

Every reader turns a bad file into a :class:`rough_map.errors.FileFormatError` that names
the file and the field concerned.
"""

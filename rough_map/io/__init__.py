"""Readers and writers: point clouds, ROS bags and traverse folders.

One module per source. Every reader turns a bad file into a
:class:`rough_map.errors.FileFormatError` that names the file and the field concerned.
"""

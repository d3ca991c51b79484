"""Simulation: images and clouds of synthetic worlds, for tests, benchmarks and demos.

:mod:`rough_map.simulate.render` renders what a stereo rig on the rover sees of a world
:class:`rough_map.types.HeightField`; :mod:`rough_map.simulate.textures` gives each terrain
class its procedural look.
"""

"""LiDAR simulator: a spinning multi-beam sensor ray-cast through random street scenes (docs/simulator.md)."""

from lidar.sim.scene import SceneConfig
from lidar.sim.sensors import Sensor, load_elevations, sensor_spec
from lidar.sim.simulate import SimConfig, simulate

__all__ = ["SceneConfig", "Sensor", "SimConfig", "load_elevations", "sensor_spec", "simulate"]

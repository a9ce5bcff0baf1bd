"""LiDAR simulator: a spinning multi-beam sensor ray-cast through random street scenes (docs/simulator.md)."""

from model.data.sim.scene import SceneConfig
from model.data.sim.sensors import Sensor, load_elevations, sensor_spec
from model.data.sim.simulate import SimConfig, simulate

__all__ = ["SceneConfig", "Sensor", "SimConfig", "load_elevations", "sensor_spec", "simulate"]

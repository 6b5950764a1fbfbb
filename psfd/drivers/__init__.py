"""Hardware drivers behind small protocols, and the fakes that replace them in tests."""

from psfd.drivers.base import Camera, CameraInfo, Position, Rail

__all__ = ["Camera", "CameraInfo", "Position", "Rail"]

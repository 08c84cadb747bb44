"""The scene's geometry: pinhole cameras and their one world-to-pixel projection (`camera`),
cameras from Blender / nerfstudio frames (`frames`)."""

from .camera import DEFAULT_MAX_SIZE, Camera, look_at, validate_pose
from .frames import camera_from_frame, cameras_from_json

__all__ = ["DEFAULT_MAX_SIZE", "Camera", "camera_from_frame", "cameras_from_json", "look_at", "validate_pose"]

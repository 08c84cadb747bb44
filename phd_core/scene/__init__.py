"""The scene's geometry: pinhole cameras, their one world-to-pixel projection, which cameras of
two lists coincide and which see none of a scene (`camera`), cameras from Blender / nerfstudio
frames (`frames`), where the scene is (`bounds`) and what the training views' masks leave of it
(`hull`), pixel rays (`rays`), quaternions (`rotations`), similarities between world frames
(`similarity`), the capture's up direction (`up`)."""

from .bounds import frustum_bounds, scene_bounds
from .camera import DEFAULT_MAX_SIZE, UNSEEN_SHARE, Camera, look_at, pose_matches, unseen_cameras, validate_pose
from .frames import camera_from_frame, cameras_from_json
from .hull import Footprint, footprint, visual_hull
from .rays import camera_rays, pixels_in_box, ray_box
from .similarity import IDENTITY, Similarity
from .up import CaptureUp, capture_up

__all__ = ["DEFAULT_MAX_SIZE", "IDENTITY", "UNSEEN_SHARE", "Camera", "CaptureUp", "Footprint", "Similarity",
           "camera_from_frame", "camera_rays", "cameras_from_json", "capture_up", "footprint", "frustum_bounds",
           "look_at", "pixels_in_box", "pose_matches", "ray_box", "scene_bounds", "unseen_cameras", "validate_pose",
           "visual_hull"]

"""Writing files: atomic writes (`files`), the one PNG encoder (`png`), zeta heat maps
(`heatmap`) and results kept beside a model (`cache`). Every file the library, the CLI or the
service writes goes through here. Reading what others wrote, within bounds: trainers' config,
camera and checkpoint files (`foreign`), the zips users hand over (`archives`) and the schemas
of the config fields the readers use (`configs`); imported from their modules."""

from .cache import ModelCache
from .files import fsync_path, write_bytes_atomic, write_json_atomic
from .heatmap import colorize, write_heatmap
from .png import png_bytes, write_png

__all__ = ["ModelCache", "colorize", "fsync_path", "png_bytes", "write_bytes_atomic", "write_heatmap",
           "write_json_atomic", "write_png"]

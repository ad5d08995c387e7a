"""Input and output: scene files in, images, progress and meshes out (re-exports only)."""

from ._export import FORMATS as FORMATS
from ._export import export_scene as export_scene
from ._export import scene_meshes as scene_meshes
from ._export import water_grid as water_grid
from ._export import water_mesh as water_mesh
from ._images import OutputError as OutputError
from ._images import atomic_path as atomic_path
from ._images import atomic_paths as atomic_paths
from ._images import check_output_set as check_output_set
from ._images import check_outputs as check_outputs
from ._images import check_writable as check_writable
from ._images import read_record as read_record
from ._images import png_bytes as png_bytes
from ._images import prefetch_imports as prefetch_imports
from ._images import read_exr as read_exr
from ._images import read_exr_layers as read_exr_layers
from ._images import recover_outputs as recover_outputs
from ._images import output_lock as output_lock
from ._images import to_srgb8 as to_srgb8
from ._images import write_exr as write_exr
from ._images import write_outputs as write_outputs
from ._images import write_png as write_png
from ._progress import Progress as Progress
from ._scene_file import SceneError as SceneError
from ._scene_file import load_scene as load_scene
from ._scene_file import scene_from_dict as scene_from_dict

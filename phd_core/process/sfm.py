"""Structure-from-motion with pycolmap (COLMAP's own code, on the CPU), stage by stage:

    features      SIFT keypoints and descriptors of every photo, into database.db; one camera
                  shared by every photo when they have one size (its focal length and lens
                  distortion estimated from all of them), else one per photo
    matching      the pairs of COLMAP's sequential generator (each photo with those 1, 2, 4,
                  ..., 512 places after it by name: its defaults, overlap 10, quadratic) or its
                  exhaustive generator (every pair), matched and geometrically verified
    mapping       incremental mapping; of the models it builds, the largest is kept
    undistortion  each registered photo warped to the PINHOLE camera COLMAP derives from its
                  lens model, cropped to the pixels the photo covers (COLMAP's image_undistorter)

Each stage reports progress(fraction of its work) as it goes: features, matching and
undistortion run as about 20 library calls over slices of their photos or pairs (a slice is
also where Ctrl-C takes effect); mapping reports each photo it registers.

Two of COLMAP's defaults are changed, for small photos (docs/formats.md, "From photos"):
the mapper's first pair needs 30 verified inliers (COLMAP: 100) and each further photo 15
(COLMAP: 30). At 200-240 px SIFT finds 80-200 features per photo, so COLMAP's thresholds
leave most of such a capture unregistered; larger photos clear both easily, and the inlier
ratio and reprojection checks that guard a registration are unchanged.
"""

from __future__ import annotations

import math
import os
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator, Sequence, TypeVar

import pycolmap
from PIL import Image

Progress = Callable[[float], None]
T = TypeVar("T")
VERSION = pycolmap.__version__

SLICES = 20                   # library calls per stage, for its progress
INIT_MIN_INLIERS = 30         # COLMAP: 100
ABS_POSE_MIN_INLIERS = 15     # COLMAP: 30


@contextmanager
def quiet_colmap() -> Iterator[None]:
    """COLMAP logs only errors while inside (its INFO lines would bury the progress bars)."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.ERROR)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def seed(value: int) -> None:
    """Seed COLMAP's random generator (RANSAC and the mapper also take the seed as an option)."""
    pycolmap.set_random_seed(value)


def _slices(items: Sequence[T], progress: Progress) -> Iterator[Sequence[T]]:
    """`items` in about SLICES slices, none smaller than the machine's thread count (each call
    runs a slice on every core); progress(fraction done) once a slice's work is done."""
    size = max(math.ceil(len(items) / SLICES), os.cpu_count() or 1)
    for start in range(0, len(items), size):
        yield items[start:start + size]
        progress(min(1.0, (start + size) / len(items)))


def extract_features(database: Path, images: Path, names: list[str], *, camera_model: str, single_camera: bool,
                     progress: Progress) -> None:
    """SIFT features of the photos `names` in `images`, into a new `database`."""
    mode = pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.PER_IMAGE
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    pycolmap.Database.open(database).close()                # import_images needs the file
    # Imported in one call, so that SINGLE makes one camera however many calls extract them.
    pycolmap.import_images(database, images, camera_mode=mode, image_names=names, options=reader)
    for part in _slices(names, progress):
        pycolmap.extract_features(database, images, image_names=list(part), camera_mode=mode, reader_options=reader)


def match_features(database: Path, *, sequential: bool, seed: int, progress: Progress) -> int:
    """Match the pairs COLMAP's sequential or exhaustive generator picks; returns their number."""
    with pycolmap.Database.open(database) as db:
        generator = (pycolmap.SequentialPairGenerator(pycolmap.SequentialPairingOptions(), db) if sequential
                     else pycolmap.ExhaustivePairGenerator(pycolmap.ExhaustivePairingOptions(), db))
        pairs = generator.all_pairs()
        names = {image.image_id: image.name for image in db.read_all_images()}
    return match_pairs(database, [(names[a], names[b]) for a, b in pairs], seed=seed, progress=progress)


def match_pairs(database: Path, pairs: Sequence[tuple[str, str]], *, seed: int, progress: Progress) -> int:
    """Match and geometrically verify the image pairs given by name; returns their number."""
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    pair_list = database.with_name("pairs.txt")
    for part in _slices(pairs, progress):
        pair_list.write_text("".join(f"{a} {b}\n" for a, b in part))
        pycolmap.match_image_pairs(database, pairing_options=pycolmap.ImportedPairingOptions(
            match_list_path=str(pair_list)), verification_options=verification)
    pair_list.unlink(missing_ok=True)
    return len(pairs)


def add_features(database: Path, images: Path, names: list[str], *, camera_model: str, progress: Progress) -> None:
    """SIFT features of the photos `names`, added to an existing `database`: a photo of the size
    of one of its cameras shares that camera (its intrinsics are refined together), any other
    gets its own."""
    with pycolmap.Database.open(database) as db:
        cameras = {(camera.width, camera.height): camera.camera_id for camera in db.read_all_cameras()}
    by_camera: dict[int | None, list[str]] = {}
    for name in names:
        with Image.open(images / name) as image:
            by_camera.setdefault(cameras.get(image.size), []).append(name)
    for camera_id, group in by_camera.items():
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        mode = pycolmap.CameraMode.PER_IMAGE
        if camera_id is not None:
            reader.existing_camera_id = camera_id
            mode = pycolmap.CameraMode.SINGLE
        pycolmap.import_images(database, images, camera_mode=mode, image_names=group, options=reader)
        for part in _slices(group, progress):
            pycolmap.extract_features(database, images, image_names=list(part), camera_mode=mode,
                                      reader_options=reader)


def map_images(database: Path, images: Path, out: Path, *, seed: int, progress: Progress,
               existing: Path | None = None) -> pycolmap.Reconstruction:
    """Incremental mapping; the model that registers the most photos, written to `out`. With
    `existing` (a reconstruction of some of the database's images) it is extended: the images it
    holds keep their poses (`fix_existing_frames`), so the capture's frame does not move, its
    cameras keep their intrinsics, the others are registered into it, and the model kept is the
    one holding its images (photos of something else may form a larger model of their own)."""
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    # One thread: the same photos give the same poses, bit for bit (on all threads a ring of 12
    # generated photos came out up to 4.4 units apart between two runs). Its price at 400 px, one
    # thread against all (2 cores): cup_colmap's 77 photos 2.4-3.3 s either way, imac_chair's 68
    # 2.1 against 2.2 s, flask_desk's 101 6.7 against 5.4 s of a 14 s run; the same photos registered.
    options.num_threads = 1
    start = pycolmap.Reconstruction(existing) if existing is not None else pycolmap.Reconstruction()
    if existing is not None:
        options.fix_existing_frames = True
        # Bundle adjustment refines intrinsics otherwise (measured: the focal length of a 300 px
        # capture moved by 0.4 % when 7 photos were added), and every earlier image, undistorted
        # again, would change under a model trained on them.
        options.constant_cameras = set(start.cameras)
    options.mapper.init_min_num_inliers = INIT_MIN_INLIERS
    options.mapper.abs_pose_min_num_inliers = ABS_POSE_MIN_INLIERS
    with pycolmap.Database.open(database) as db:
        total = db.num_images() - start.num_reg_images()       # the photos left to register
    registered = 0

    def next_image() -> None:
        nonlocal registered
        registered += 1
        progress(min(1.0, registered / max(total, 1)))

    scratch = out.parent / "models"
    scratch.mkdir(parents=True)
    models = pycolmap.incremental_mapping(database, images, scratch, options, input_path=existing or "",
                                          next_image_callback=next_image)
    shutil.rmtree(scratch)
    out.mkdir(parents=True)
    if not models:
        return pycolmap.Reconstruction()
    held = set(start.reg_image_ids())

    def rank(model: pycolmap.Reconstruction) -> tuple[int, int]:
        return len(held & set(model.reg_image_ids())), model.num_reg_images()

    best = max(models.values(), key=rank)
    best.write(out)
    return best


def undistort(model: Path, images: Path, out: Path, names: list[str], progress: Progress) -> None:
    """The photos `names` of `model` undistorted to PINHOLE: out/images/ and out/sparse/0/."""
    scratch = out / "undistorted"
    for part in _slices(names, progress):
        pycolmap.undistort_images(scratch, model, images, image_names=list(part), output_type="COLMAP")
    (scratch / "images").rename(out / "images")
    (out / "sparse").mkdir()
    (scratch / "sparse").rename(out / "sparse" / "0")
    shutil.rmtree(scratch)                     # COLMAP's stereo/ folder and scripts for its dense steps

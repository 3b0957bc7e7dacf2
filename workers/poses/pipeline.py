"""The stages from photos to a posed scene, each resumable: features, matching, mapping,
alignment, export. A work folder beside the output (`.NAME.poses/`) holds COLMAP's database, the
kept model and `state.json` (the stages finished); a run started again on the same photos and
settings goes on from the last finished stage (within features and matching, from the last
finished chunk). The scene folder appears whole at the end, by a rename, or not at all.

Runs in the pycolmap process (process.py); `report` receives plain dicts (events)."""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np

from model.errors import Failed
from model.scenes.errors import SceneError
from workers.poses import geodesy
from workers.poses.pairs import MatchPlan, plan
from workers.poses.photos import Photos, scan
from workers.poses.settings import STAGES, PosesConfig

GEOREFERENCE = "georeference.json"  # beside sparse/: the model is in east-north-up metres
REPORT = "poses.json"  # beside sparse/: how the poses were found
MIN_INLIERS = 15  # the mappers' min_num_matches: a pair with fewer verified matches is not used
CHUNKS = 20  # features and matching each run in about this many chunks: progress and resume points
Report = Callable[[dict], None]


def work_folder(out: Path) -> Path:
    return out.parent / f".{out.name}.poses"


class Run:
    """One pass over the stages; `state` is what a later pass resumes from."""

    def __init__(self, photos: Photos, out: Path, config: PosesConfig, report: Report):
        import pycolmap  # only in the pycolmap process

        self.colmap = pycolmap
        self.photos, self.out, self.config, self.report = photos, out, config, report
        self.work = work_folder(out)
        self.lock = _hold_lock(self.work.with_name(self.work.name + ".lock"), out)
        self.database = self.work / "database.db"
        self.model_dir = self.work / "model"
        self.state = self._load_state()
        pycolmap.set_random_seed(config.seed)

    # -- state ----------------------------------------------------------------------------------

    def _fingerprint(self) -> str:
        """The photos (names, sizes, bytes on disk) and the settings that shape the result."""
        h = hashlib.sha256()
        for p in self.photos.photos:
            h.update(f"{p.name}\0{p.size}\0{p.path.stat().st_size}\n".encode())
        shaping = self.config.model_dump(exclude={"time_limit_s", "memory_limit_mb", "threads"})
        h.update(json.dumps(shaping, sort_keys=True).encode())
        return h.hexdigest()

    def _load_state(self) -> dict:
        fingerprint = self._fingerprint()
        path = self.work / "state.json"
        if path.is_file():
            state = json.loads(path.read_text())
            if state.get("fingerprint") == fingerprint:
                if state["done"]:
                    self.log(f"resuming after {state['done'][-1]} (work folder {self.work})")
                return state
            self.log(f"{self.work} was made from other photos or settings: starting over")
        shutil.rmtree(self.work, ignore_errors=True)
        self.work.mkdir(parents=True)
        return {"fingerprint": fingerprint, "done": [], "seconds": {}}

    def _save_state(self) -> None:
        tmp = self.work / "state.json.tmp"
        tmp.write_text(json.dumps(self.state, indent=1))
        os.replace(tmp, self.work / "state.json")

    # -- events ---------------------------------------------------------------------------------

    def log(self, message: str) -> None:
        self.report({"event": "log", "message": message})

    def progress(self, stage: str, done: int, total: int, unit: str) -> None:
        self.report(
            {"event": "progress", "stage": stage, "done": done, "total": total, "unit": unit}
        )

    # -- the stages -----------------------------------------------------------------------------

    def run(self) -> dict:
        for warning in self.photos.warnings():
            self.report({"event": "warning", "message": warning})
        for index, stage in enumerate(STAGES):
            self.report({"event": "stage", "stage": stage, "index": index, "stages": len(STAGES)})
            if stage in self.state["done"]:
                self.progress(stage, 1, 1, "done before")
                continue
            started = time.perf_counter()
            getattr(self, stage)()
            self.state["seconds"][stage] = round(
                self.state["seconds"].get(stage, 0.0) + time.perf_counter() - started, 2
            )
            self.state["done"].append(stage)
            if stage != "export":
                self._save_state()
        summary = self.state["summary"]
        _write_json(self.out / REPORT, summary)  # again, now with the export's own time
        shutil.rmtree(self.work, ignore_errors=True)
        Path(self.lock.name).unlink(missing_ok=True)
        self.lock.close()
        return summary

    def _camera_mode(self) -> Any:
        """One camera for photos of one size from one camera (or with no camera EXIF at all: the
        frames of a video); else COLMAP's own grouping, a camera per size and EXIF camera (it would
        give every photo without EXIF a camera of its own)."""
        one = self.photos.summary()["cameras"] == 1
        return self.colmap.CameraMode.SINGLE if one else self.colmap.CameraMode.AUTO

    def _reader_options(self) -> Any:
        return self.colmap.ImageReaderOptions(camera_model=self.config.camera_model)

    def features(self) -> None:
        pycolmap = self.colmap
        names = self.photos.names
        if not self.state.get("imported"):  # a database cut short while importing is redone
            self.database.unlink(missing_ok=True)
            pycolmap.Database.open(self.database).close()  # a new, empty database
            pycolmap.import_images(
                self.database,
                self.photos.folder,
                camera_mode=self._camera_mode(),
                image_names=names,
                options=self._reader_options(),
            )
            self._exif_focals()
            self.state["imported"] = True
            self._save_state()
        options = pycolmap.FeatureExtractionOptions()
        options.max_image_size = self.config.max_image_size
        options.num_threads = self.config.threads
        with pycolmap.Database.open(self.database) as db:
            ids = {im.name: im.image_id for im in db.read_all_images()}
            todo = [n for n in names if not db.exists_keypoints(ids[n])]
        size = max(1, -(-len(names) // CHUNKS))
        done = len(names) - len(todo)
        self.progress("features", done, len(names), "photos")
        for start in range(0, len(todo), size):
            chunk = todo[start : start + size]
            pycolmap.extract_features(
                self.database,
                self.photos.folder,
                image_names=chunk,
                camera_mode=self._camera_mode(),
                reader_options=self._reader_options(),
                extraction_options=options,
                device=pycolmap.Device.cpu,
            )
            done += len(chunk)
            self.progress("features", done, len(names), "photos")
        with pycolmap.Database.open(self.database) as db:
            keypoints = {
                im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()
            }
        empty = [n for n in names if keypoints.get(n, 0) == 0]
        if empty:
            self.log(f"{len(empty)} photos gave no features (blank or featureless?): {empty[0]}")
        self.state["cameras"] = self._camera_count()

    def _exif_focals(self) -> None:
        """Each camera starts from its photos' EXIF focal length where Pillow read one (COLMAP's
        own guess stays where none was)."""
        by_name = {p.name: p for p in self.photos.photos}
        with self.colmap.Database.open(self.database) as db:
            seen = set()
            for image in db.read_all_images():
                focal = by_name[image.name].exif.focal_px
                if focal is None or image.camera_id in seen:
                    continue
                seen.add(image.camera_id)
                camera = db.read_camera(image.camera_id)
                params = [float(v) for v in camera.params]
                for index in camera.focal_length_idxs():
                    params[index] = focal
                camera.params = params
                camera.has_prior_focal_length = True
                db.update_camera(camera)

    def _camera_count(self) -> int:
        with self.colmap.Database.open(self.database) as db:
            return db.num_cameras()

    def _gps_positions(self) -> tuple[np.ndarray | None, geodesy.Geodetic | None]:
        """Each photo's GPS in metres east, north and up of their mean (None without GPS on every
        photo, or with gps=off)."""
        if self.config.gps == "off" or len(self.photos.with_gps) < len(self.photos):
            return None, None
        points = np.array([p.exif.gps for p in self.photos.photos], dtype=np.float64)
        origin = geodesy.centre(points)
        return geodesy.to_enu(points, origin), origin

    def matching(self) -> None:
        pycolmap = self.colmap
        positions, _ = self._gps_positions()
        try:
            chosen: MatchPlan = plan(self.photos, self.config, positions)
        except ValueError as exc:
            raise SceneError(self.photos.folder, str(exc)) from None
        self.log(f"matcher: {chosen.matcher} ({chosen.reason}); {len(chosen.pairs):,} pairs")
        self.state["matcher"] = {"name": chosen.matcher, "reason": chosen.reason}
        names = self.photos.names
        with pycolmap.Database.open(self.database) as db:
            ids = {im.name: im.image_id for im in db.read_all_images()}
            todo = [
                (i, j)
                for i, j in chosen.pairs
                if not db.exists_two_view_geometry(ids[names[i]], ids[names[j]])
            ]
        options = pycolmap.FeatureMatchingOptions()
        options.num_threads = self.config.threads
        total = len(chosen.pairs)
        done = total - len(todo)
        size = max(50, -(-total // CHUNKS))
        pair_file = self.work / "pairs.txt"
        self.progress("matching", done, total, "pairs")
        for start in range(0, len(todo), size):
            chunk = todo[start : start + size]
            pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in chunk))
            pycolmap.match_image_pairs(
                self.database,
                matching_options=options,
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pair_file)),
                device=pycolmap.Device.cpu,
            )
            done += len(chunk)
            self.progress("matching", done, total, "pairs")
        with pycolmap.Database.open(self.database) as db:
            _, geometries = db.read_two_view_geometries()
            self.state["verified_pairs"] = sum(
                len(g.inlier_matches) >= MIN_INLIERS for g in geometries
            )

    def mapping(self) -> None:
        pycolmap = self.colmap
        n = len(self.photos)
        sparse = self.work / "sparse"
        shutil.rmtree(sparse, ignore_errors=True)
        sparse.mkdir()
        self.progress("mapping", 0, n, "photos registered")
        if self.config.mapper == "global":
            options = pycolmap.GlobalPipelineOptions()
            options.random_seed = self.config.seed
            options.num_threads = self.config.threads
            models = pycolmap.global_mapping(self.database, self.photos.folder, sparse, options)
        else:
            options = pycolmap.IncrementalPipelineOptions()
            options.random_seed = self.config.seed
            options.num_threads = self.config.threads
            options.min_model_size = 3
            registered = [0]

            def next_image() -> None:
                registered[0] += 1
                self.progress("mapping", min(registered[0], n), n, "photos registered")

            models = pycolmap.incremental_mapping(
                self.database, self.photos.folder, sparse, options, next_image_callback=next_image
            )
        sizes = sorted(((m.num_reg_images(), k) for k, m in models.items()), reverse=True)
        if not sizes:
            raise SceneError(
                self.photos.folder,
                f"no model could be built: {self.state.get('verified_pairs', 0)} photo pairs "
                "share enough matched features (do the photos overlap? are they of one place?)",
            )
        kept, key = sizes[0]
        share = kept / n
        pieces = [s for s, _ in sizes[1:]]
        self.state["models"] = [s for s, _ in sizes]
        if pieces:
            self.log(
                f"the photos broke into {len(sizes)} models "
                f"({', '.join(map(str, [kept, *pieces]))} photos): the largest is kept"
            )
        if share < self.config.min_registered:
            raise SceneError(
                self.photos.folder,
                f"only {kept} of {n} photos ({share:.0%}) registered in the largest model, under "
                f"min_registered {self.config.min_registered:.0%}"
                + (f" (other models: {', '.join(map(str, pieces))} photos)" if pieces else "")
                + ": the photos overlap too little, or show several places",
            )
        self.progress("mapping", kept, n, "photos registered")
        shutil.rmtree(self.model_dir, ignore_errors=True)
        self.model_dir.mkdir()
        models[key].write(self.model_dir)
        self.state["registered"] = kept

    def alignment(self) -> None:
        self.progress("alignment", 0, 1, "model")
        self._align()
        self.progress("alignment", 1, 1, "model")

    def _align(self) -> None:
        pycolmap = self.colmap
        model = pycolmap.Reconstruction(self.model_dir)
        if self.config.gps == "off":
            self.state["georeference"] = None
            return
        with_gps = [p for p in self.photos.with_gps if model.find_image_with_name(p.name)]
        if len(with_gps) < 3:
            if self.photos.with_gps:
                self.log(f"{len(with_gps)} registered photos carry GPS; 3 are needed to align")
            self.state["georeference"] = None
            return
        points = np.array([p.exif.gps for p in self.photos.with_gps], dtype=np.float64)
        origin = geodesy.centre(points)
        enu = geodesy.to_enu(np.array([p.exif.gps for p in with_gps]), origin)
        ransac = pycolmap.RANSACOptions()
        ransac.max_error = self.config.gps_max_error_m
        ransac.random_seed = self.config.seed
        names = [p.name for p in with_gps]
        sim = pycolmap.align_reconstruction_to_locations(model, names, enu, 3, ransac)
        if sim is None:
            self.log(
                f"the GPS of {len(names)} photos does not fit the model within "
                f"{self.config.gps_max_error_m} m: the scene keeps the cameras' own frame"
            )
            self.state["georeference"] = None
            return
        model.transform(sim)
        centres = np.array([model.find_image_with_name(n).projection_center() for n in names])
        errors = np.linalg.norm(centres - enu, axis=1)
        self.state["georeference"] = {
            "frame": "ENU",
            "units": "metres",
            "axes": "x east, y north, z up",
            "origin": {
                "latitude": origin.latitude,
                "longitude": origin.longitude,
                "altitude": origin.altitude,
            },
            "photos_with_gps": len(names),
            "scale": float(sim.scale),
            "gps_error_m": {"median": float(np.median(errors)), "max": float(errors.max())},
        }
        self.log(
            f"aligned to east-north-up metres by the GPS of {len(names)} photos: median error "
            f"{np.median(errors):.2f} m, worst {errors.max():.2f} m"
        )
        model.write(self.model_dir)

    def export(self) -> None:
        self.progress("export", 0, 1, "scene folder")
        self._export()
        self.progress("export", 1, 1, "scene folder")

    def _export(self) -> None:
        model = self.colmap.Reconstruction(self.model_dir)
        partial = self.out.parent / f".{self.out.name}.partial"
        shutil.rmtree(partial, ignore_errors=True)
        (partial / "sparse" / "0").mkdir(parents=True)
        model.write(partial / "sparse" / "0")
        registered = {model.image(i).name for i in model.reg_image_ids()}
        for photo in self.photos.photos:
            if photo.name not in registered:
                continue
            target = partial / "images" / photo.name
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.link(photo.path, target)
            except OSError:  # another file system, or links not allowed
                shutil.copy2(photo.path, target)
        georeference = self.state.get("georeference")
        if georeference:
            _write_json(partial / GEOREFERENCE, georeference)
        n = len(self.photos)
        summary = {
            "photos": n,
            "registered": len(registered),
            "unregistered": sorted(set(self.photos.names) - registered),
            "models": self.state.get("models", []),
            "cameras": model.num_cameras(),
            "points": model.num_points3D(),
            "mean_reprojection_error_px": round(float(model.compute_mean_reprojection_error()), 4),
            "matcher": self.state.get("matcher"),
            "verified_pairs": self.state.get("verified_pairs"),
            "mapper": self.config.mapper,
            "georeference": georeference,
            "warnings": self.photos.warnings(),
            "seconds": self.state["seconds"],
            "config": self.config.model_dump(),
        }
        _write_json(partial / REPORT, summary)
        if self.out.exists():
            self.out.rmdir()  # an empty folder given as the output (checked before the run)
        os.replace(partial, self.out)
        self.state["summary"] = summary


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def _hold_lock(path: Path, out: Path) -> TextIO:
    """One run at a time posing into `out`: a second is refused while the first holds the lock
    (released when its process ends, however it ends)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle = open(path, "a")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise Failed(f"another run is finding poses for {out}: wait for it or stop it") from None
    return handle


def check_output(out: Path) -> None:
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SceneError(out, "the output must not exist or be an empty folder")


def find_poses(photos_dir: Path, out: Path, config: PosesConfig, report: Report) -> dict:
    """Photos in, a COLMAP scene folder out (images/, sparse/0/, poses.json, and georeference.json
    when GPS placed it): the summary of poses.json."""
    out = Path(out)
    check_output(out)
    photos = scan(Path(photos_dir), config)
    report({"event": "log", "message": _describe(photos)})
    return Run(photos, out, config, report).run()


def _describe(photos: Photos) -> str:
    s = photos.summary()
    sizes = ", ".join(f"{k} ({v})" for k, v in s["sizes"].items())
    return (
        f"{s['photos']} photos, {sizes}; {s['with_focal']} with an EXIF focal length, "
        f"{s['with_gps']} with GPS"
    )

"""Property tests of the scene readers: mutated scene files of every metadata format (types swapped,
fields removed, non-finite and extreme numbers, odd shapes, degenerate geometry) either load into a
scene whose numbers are finite and whose box has volume, or are refused with a SceneError. Never
another exception: in the service that would be a 500, or a worker failing after the upload was
accepted."""

import json
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from model.scenes import SceneError, load_scene
from tests.model.scenes.test_bad_input import look_at_drb

SETTINGS = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
W, H, FOCAL = 16, 12, 20.0

hostile_numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, -1.0, 1e-300, 1e-50, 1e39, 1e308, -1e308, 2.0**63, float("nan")]),
    st.integers(min_value=-(10**40), max_value=10**40),
)
hostile_json = st.one_of(
    hostile_numbers,
    st.none(),
    st.booleans(),
    st.text(max_size=8),
    st.lists(hostile_numbers, max_size=5),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def accepted_scene_is_sane(root) -> None:
    """The property: a SceneError, or a scene with finite numbers and a box that has volume."""
    try:
        scene = load_scene(root)
    except SceneError as error:
        assert len(str(error)) < 2000, "a refusal is a sentence, not a dump"
        return
    assert math.isfinite(scene.normalization.scale) and scene.normalization.scale > 0
    assert torch.isfinite(scene.bounds.aabb).all()
    assert bool(((scene.bounds.aabb[1] - scene.bounds.aabb[0]) > 0).all())
    for views in scene.splits.values():
        assert (
            torch.isfinite(views.cameras.c2w).all()
            and torch.isfinite(views.cameras.intrinsics).all()
        )
        assert torch.isfinite(views.cameras.distortion).all()


def tiny_images(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        Image.new("RGB", (W, H), (30 * i, 90, 120)).save(folder / name)


# --- nerfstudio
# -------------------------------------------------------------------------------------------------


def opengl_look_at(position):
    p = torch.tensor(position)
    back = p / p.norm()
    right = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0]), back)
    right = right / right.norm()
    up = torch.linalg.cross(back, right)
    return torch.cat(
        [torch.stack([right, up, back, p], dim=1), torch.tensor([[0.0, 0, 0, 1]])]
    ).tolist()


@pytest.fixture
def nerfstudio_root(tmp_path):
    root = tmp_path / "ns"
    names = [f"f{i}.png" for i in range(5)]
    tiny_images(root / "images", names)
    positions = [[3 * math.cos(a), 3 * math.sin(a), 1.5] for a in np.linspace(0, 2, len(names))]
    frames = [
        {"file_path": f"images/{n}", "transform_matrix": opengl_look_at(p)}
        for n, p in zip(names, positions)
    ]
    data = {
        "camera_model": "OPENCV",
        "fl_x": FOCAL,
        "fl_y": FOCAL,
        "cx": W / 2,
        "cy": H / 2,
        "w": W,
        "h": H,
        "k1": 0.0,
        "frames": frames,
        "train_filenames": [f"images/{n}" for n in names[1:]],
        "val_filenames": [f"images/{names[0]}"],
    }
    (root / "transforms.json").write_text(json.dumps(data))
    return root, data


NERFSTUDIO_FIELDS = [
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "k1",
    "k2",
    "p1",
    "p2",
    "k3",
    "camera_model",
    "train_filenames",
    "val_filenames",
    "frames",
]


@SETTINGS
@given(
    mutations=st.lists(
        st.tuples(
            st.sampled_from(
                NERFSTUDIO_FIELDS
                + ["frame.fl_x", "frame.file_path", "frame.transform_matrix", "matrix"]
            ),
            st.one_of(st.just("<deleted>"), hostile_json),
        ),
        min_size=1,
        max_size=3,
    ),
    frame=st.integers(0, 4),
    row=st.integers(0, 3),
    column=st.integers(0, 3),
)
def test_mutated_nerfstudio_files_load_sanely_or_are_refused(
    nerfstudio_root, mutations, frame, row, column
):
    root, good = nerfstudio_root
    data = json.loads(json.dumps(good))
    for where, value in mutations:
        if where == "matrix":
            data["frames"][frame]["transform_matrix"][row][column] = value
            continue
        target = data["frames"][frame] if where.startswith("frame.") else data
        key = where.removeprefix("frame.")
        if value == "<deleted>":
            target.pop(key, None)
        else:
            target[key] = value
    (root / "transforms.json").write_text(json.dumps(data))
    accepted_scene_is_sane(root)


# --- Mega-NeRF
# -------------------------------------------------------------------------------------------------


@pytest.fixture
def meganerf_root(tmp_path):
    root = tmp_path / "mega"
    root.mkdir()
    torch.save(
        {"origin_drb": torch.zeros(3, dtype=torch.float64), "pose_scale_factor": 10.0},
        root / "coordinates.pt",
    )
    positions = ([-1.0, 0.5, 0.0], [-1.0, -0.5, 0.0], [-1.0, 0.0, 0.5])
    for i, split in enumerate(("train", "train", "val")):
        (root / split / "metadata").mkdir(parents=True, exist_ok=True)
        tiny_images(root / split / "rgbs", [f"{i:06d}.png"])
        torch.save(
            {
                "W": W,
                "H": H,
                "intrinsics": torch.tensor([FOCAL, FOCAL, W / 2, H / 2]),
                "c2w": look_at_drb(positions[i]),
            },
            root / split / "metadata" / f"{i:06d}.pt",
        )
    return root


hostile_tensors = st.one_of(
    st.builds(
        lambda n, v: torch.full((n,), v),
        st.integers(0, 17),
        hostile_numbers.filter(lambda v: isinstance(v, float) or abs(v) < 2**62),
    ),
    st.builds(lambda a, b: torch.zeros(1).expand(a, b), st.integers(1, 5000), st.integers(1, 5000)),
    st.sampled_from(
        [
            torch.ones(4, dtype=torch.complex64),
            torch.ones(3, 4, dtype=torch.bool),
            torch.eye(4),
            torch.eye(4)[:3] * float("nan"),
            torch.ones(2, 2),
        ]
    ),
)
META_FIELDS = ["W", "H", "intrinsics", "c2w", "distortion"]


@SETTINGS
@given(
    field=st.sampled_from(META_FIELDS + ["origin_drb", "pose_scale_factor"]),
    value=st.one_of(st.just("<deleted>"), hostile_json, hostile_tensors),
    view=st.integers(0, 2),
)
def test_mutated_meganerf_files_load_sanely_or_are_refused(meganerf_root, field, value, view):
    root = meganerf_root
    split = "val" if view == 2 else "train"
    path = (
        root / "coordinates.pt"
        if field in ("origin_drb", "pose_scale_factor")
        else root / split / "metadata" / f"{view:06d}.pt"
    )
    original = path.read_bytes()
    data = torch.load(path, weights_only=True)
    if value == "<deleted>":
        data.pop(field, None)
    else:
        data[field] = value
    torch.save(data, path)
    try:
        accepted_scene_is_sane(root)
    finally:
        path.write_bytes(original)


# --- LLFF
# -------------------------------------------------------------------------------------------------


@pytest.fixture
def llff_root(tmp_path):
    root = tmp_path / "llff"
    names = [f"image{i:03d}.png" for i in range(4)]
    tiny_images(root / "images", names)
    rows = []
    for x in np.linspace(-0.3, 0.3, len(names)):
        # LLFF's [down, right, back | t | h, w, f], looking along -back at the origin from z = 4
        pose = np.array(
            [[0, 1, 0, x, H], [-1, 0, 0, 0, W], [0, 0, 1, 4.0, FOCAL]], dtype=np.float64
        )
        rows.append(np.concatenate([pose.reshape(-1), [2.0, 6.0]]))
    np.save(root / "poses_bounds.npy", np.stack(rows))
    return root


@SETTINGS
@given(
    row=st.integers(0, 3),
    column=st.integers(0, 16),
    value=hostile_numbers.filter(lambda v: isinstance(v, float) or abs(v) < 1e300),
)
def test_mutated_llff_poses_load_sanely_or_are_refused(llff_root, row, column, value):
    path = llff_root / "poses_bounds.npy"
    original = np.load(path)
    poses = original.copy()
    poses[row, column] = float(value)
    np.save(path, poses)
    try:
        accepted_scene_is_sane(llff_root)
    finally:
        np.save(path, original)


# --- COLMAP
# -------------------------------------------------------------------------------------------------


@pytest.fixture
def colmap_root(tmp_path):
    from tests.model.scenes.test_colmap import tiny_model, write_scene

    return write_scene(tmp_path / "colmap", tiny_model(6, ("OPENCV", "SIMPLE_RADIAL")), "txt")


@SETTINGS
@given(
    name=st.sampled_from(["cameras.txt", "images.txt", "points3D.txt"]),
    line=st.integers(0, 40),
    word=st.integers(0, 12),
    value=st.one_of(
        st.just("<deleted>"), hostile_numbers.map(repr), st.text(max_size=6), st.just("")
    ),
)
def test_mutated_colmap_text_models_load_sanely_or_are_refused(
    colmap_root, name, line, word, value
):
    path = colmap_root / "sparse" / "0" / name
    original = path.read_text()
    lines = original.splitlines()
    records = [i for i, text in enumerate(lines) if not text.startswith("#")]
    at = records[line % len(records)]
    words = lines[at].split(" ")
    if value == "<deleted>":
        del words[word % len(words)]
    else:
        words[word % len(words)] = value
    lines[at] = " ".join(words)
    path.write_text("\n".join(lines) + "\n")
    try:
        accepted_scene_is_sane(colmap_root)
    finally:
        path.write_text(original)


@SETTINGS
@given(
    name=st.sampled_from(["cameras.bin", "images.bin", "points3D.bin"]),
    at=st.floats(0.0, 1.0),
    data=st.binary(min_size=1, max_size=8),
    cut=st.booleans(),
)
def test_mutated_colmap_binary_models_load_sanely_or_are_refused(tmp_path, name, at, data, cut):
    from tests.model.scenes.test_colmap import tiny_model, write_scene

    root = tmp_path / "colmap-bin"
    if not root.exists():
        write_scene(root, tiny_model(6, ("OPENCV", "SIMPLE_RADIAL")), "bin")
    path = root / "sparse" / "0" / name
    original = path.read_bytes()
    offset = int(at * (len(original) - 1))
    # overwrite some bytes in place, or cut the file there
    path.write_bytes(
        original[:offset] if cut else original[:offset] + data + original[offset + len(data) :]
    )
    try:
        accepted_scene_is_sane(root)
    finally:
        path.write_bytes(original)


def test_the_fixtures_themselves_load(nerfstudio_root, meganerf_root, llff_root, colmap_root):
    for root in (nerfstudio_root[0], meganerf_root, llff_root, colmap_root):
        scene = load_scene(root)
        assert scene.bounds.aabb.shape == (2, 3) and len(scene.train) >= 2

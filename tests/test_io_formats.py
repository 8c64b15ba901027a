"""One test per capture reader on small generated files in that format (random SMPL / SMPL-X model files, never
licensed ones), format detection, and the Rh/Th -> SMPL global_orient/transl conversion checked against the
vertices the fit implies (v = R(Rh) · V_local + Th)."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from avatarctl.body.motion import BodyMotion
from avatarctl.errors import InputError
from avatarctl.geometry.cameras import Camera
from fixtures.smpl import write_random_smpl_npz
from fixtures.captures import plate, render, ring_cameras

SIZE = 112


def rodrigues(aa: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(aa, np.float64).reshape(3, 1))[0]


@pytest.fixture(scope="module")
def smpl(tmp_path_factory):
    from avatarctl.body.smpl import SmplBody

    path = write_random_smpl_npz(tmp_path_factory.mktemp("smpl") / "SMPL_NEUTRAL.npz", "smpl", seed=3)
    return path, SmplBody.from_file(path, kind="smpl")


def random_rhth(n: int, seed: int = 0, root_pose: bool = False):
    rng = np.random.default_rng(seed)
    poses = rng.normal(0, 0.2, (n, 72))
    if not root_pose:
        poses[:, :3] = 0.0  # ZJU / EasyMocap put the global rotation into Rh
    Rh = rng.normal(0, 0.6, (n, 3))
    Th = np.array([0.05, -0.05, 0.0]) + rng.normal(0, 0.05, (n, 3))  # the random body stays in view
    shapes = rng.normal(0, 1.0, 10)
    return Rh, Th, poses, shapes


def implied_vertices(body, Rh, Th, poses, shapes) -> np.ndarray:
    """[frames, V, 3] v = R(Rh) · SMPL(poses, shapes, transl = 0) + Th (the EasyMocap definition)."""
    n = len(Rh)
    local = body.pose(BodyMotion(body_model="smpl", frame_index=np.arange(n), global_orient=poses[:, :3],
                                 body_pose=poses[:, 3:], transl=np.zeros((n, 3)), betas=shapes)).vertices.double()
    R = np.stack([rodrigues(r) for r in Rh])
    return np.einsum("fij,fvj->fvi", R, local.numpy()) + Th[:, None]


def write_frames(cams: list[Camera], verts: np.ndarray, faces: np.ndarray, image_path, mask_path,
                 mask_scale: int = 255) -> None:
    """Render every camera x frame (distorted geometry) and write images and masks via the path callables."""
    for ci, cam in enumerate(cams):
        bg = plate(cam, ci)
        for f in range(len(verts)):
            rgb, sil = render(cam, verts[f], faces, bg)
            for p, write in ((image_path(cam, f), lambda p: cv2.imwrite(str(p), rgb[..., ::-1])),
                             (mask_path(cam, f), lambda p: cv2.imwrite(str(p), sil.astype(np.uint8) * mask_scale))):
                p.parent.mkdir(parents=True, exist_ok=True)
                assert write(p)


def ingest(capture: Path, project: Path, **kw):
    from avatarctl.ingest.config import IngestConfig
    from avatarctl.ingest.pipeline import run_ingest

    return run_ingest(IngestConfig(capture=capture, project=project, contact_sheet=False, **kw))


# ---- Rh/Th conversion ----------------------------------------------------------------------------------------
def test_rhth_conversion_is_exact_for_rigid_points():
    """Pure math: R(Rh)·(R0 (x − J0) + J0) + Th == R_g (x − J0) + J0 + transl for any point x."""
    from avatarctl.ingest.fits import rhth_to_smpl

    rng = np.random.default_rng(1)
    Rh, Th, R0, J0 = rng.normal(0, 1, (5, 3)), rng.normal(0, 1, (5, 3)), rng.normal(0, 1, (5, 3)), rng.normal(0, 1, 3)
    go, transl = rhth_to_smpl(Rh, Th, R0, J0)
    x = rng.normal(0, 1, (7, 3))
    for i in range(5):
        want = (rodrigues(Rh[i]) @ (rodrigues(R0[i]) @ (x - J0).T + J0[:, None])).T + Th[i]
        got = (rodrigues(go[i]) @ (x - J0).T).T + J0 + transl[i]
        np.testing.assert_allclose(got, want, atol=1e-9)
    # ignoring the pelvis offset (transl = Th) would be wrong whenever J0 != 0 and Rh != 0
    assert np.abs(transl - Th).max() > 1e-3


@pytest.mark.parametrize("root_pose", [False, True])
def test_rhth_conversion_matches_the_vertices_the_fit_implies(smpl, root_pose):
    from avatarctl.ingest.fits import to_body_motion
    from avatarctl.io.capture import RhThFits

    _, body = smpl
    Rh, Th, poses, shapes = random_rhth(4, seed=2, root_pose=root_pose)
    fits = RhThFits("smpl", np.arange(4), Rh, Th, poses, shapes, where="test")
    motion = to_body_motion(fits, "smpl", body)
    got = body.pose(motion).vertices.double().numpy()
    want = implied_vertices(body, Rh, Th, poses, shapes)
    assert np.abs(want).max() > 0.5
    np.testing.assert_allclose(got, want, atol=2e-5)


# ---- ZJU-MoCap ------------------------------------------------------------------------------------------------
def make_zju(root: Path, body, frames: int = 3, new_params: bool = True):
    cams = [Camera(name=f"Camera_B{i + 1}", K=c.K, R=c.R, T=c.T, width=c.width, height=c.height, dist=c.dist)
            for i, c in enumerate(ring_cameras(3, SIZE))]
    Rh, Th, poses, shapes = random_rhth(frames, seed=5)
    verts = implied_vertices(body, Rh, Th, poses, shapes)
    write_frames(cams, verts, body.faces.numpy(), lambda c, f: root / c.name / f"{f:06d}.jpg",
                 lambda c, f: root / "mask_cihp" / c.name / f"{f:06d}.png", mask_scale=1)
    annots = {"cams": {"K": [c.K for c in cams], "D": [c.dist.reshape(5, 1) for c in cams],
                       "R": [c.R for c in cams], "T": [c.T.reshape(3, 1) * 1000.0 for c in cams]},
              "ims": [{"ims": [f"{c.name}/{f:06d}.jpg" for c in cams]} for f in range(frames)]}
    np.save(root / "annots.npy", np.array(annots, dtype=object), allow_pickle=True)
    params = root / ("new_params" if new_params else "params")
    params.mkdir()
    for f in range(frames):
        np.save(params / f"{f}.npy", np.array({"Rh": Rh[f:f + 1], "Th": Th[f:f + 1], "poses": poses[f:f + 1],
                                               "shapes": shapes[None]}, dtype=object), allow_pickle=True)
    return cams


def test_zju_reader_and_ingest(smpl, tmp_path):
    from avatarctl.io.detect import detect_format
    from avatarctl.io.project_io import load_project_capture
    from avatarctl.project import Project

    path, body = smpl
    cap = tmp_path / "zju"
    cams = make_zju(cap, body)
    assert detect_format(cap)[0] == "zju"
    res = ingest(cap, tmp_path / "proj", body_model_path=path)
    assert res.format == "zju" and res.body_model == "smpl" and res.masks_source == "files"
    assert res.vertices_inside_masks > 0.99, res.vertices_inside_masks  # T mm->m and Rh/Th conversion correct
    pc = load_project_capture(Project.open(tmp_path / "proj"))
    np.testing.assert_allclose(pc.cameras["Camera_B2"].T, cams[1].T, atol=1e-9)  # metres
    assert pc.frames == [0, 1, 2]
    assert Project.open(tmp_path / "proj").manifest.body_model.path == str(path.resolve())


def test_zju_313_frame_names():
    from avatarctl.io.zju import zju_frame_number

    assert zju_frame_number("Camera (1)/CoreView_313_Camera_(1)_0001_2019-08-23_16-08-50.592.jpg") == 0
    assert zju_frame_number("Camera_B3/000123.jpg") == 123
    from avatarctl.io.capture import safe_camera_name

    assert safe_camera_name("Camera (12)") == "Camera_12"
    with pytest.raises(InputError):
        zju_frame_number("Camera_B1/frame.jpg")


# ---- EasyMocap with smpl/*.json ---------------------------------------------------------------------------------
def test_easymocap_smpl_json_reader_and_ingest(smpl, tmp_path):
    from avatarctl.io.easymocap import write_easymocap_cameras
    from avatarctl.io.easymocap_fits import read_easymocap_smpl_dir

    path, body = smpl
    cap = tmp_path / "em"
    cams = ring_cameras(3, SIZE)
    write_easymocap_cameras(cap, cams)
    Rh, Th, poses, shapes = random_rhth(3, seed=7, root_pose=True)
    verts = implied_vertices(body, Rh, Th, poses, shapes)
    write_frames(cams, verts, body.faces.numpy(), lambda c, f: cap / "images" / c.name / f"{f:06d}.jpg",
                 lambda c, f: cap / "masks" / c.name / f"{f:06d}.png")
    (cap / "smpl").mkdir()
    for f in range(3):
        me = {"id": 0, "Rh": Rh[f:f + 1].tolist(), "Th": Th[f:f + 1].tolist(), "poses": poses[f:f + 1].tolist(),
              "shapes": shapes[None].tolist()}
        other = dict(me, id=1, Th=[[9.0, 9.0, 9.0]])
        data = [other, me] if f != 1 else {"annots": [other, me]}  # both layouts; person id 0 is used
        (cap / "smpl" / f"{f:06d}.json").write_text(json.dumps(data))
    fits = read_easymocap_smpl_dir(cap / "smpl")
    np.testing.assert_allclose(fits.Th, Th)
    res = ingest(cap, tmp_path / "proj", body_model="smpl", body_model_path=path)
    assert res.vertices_inside_masks > 0.99, res.vertices_inside_masks


def test_easymocap_json_errors(tmp_path):
    from avatarctl.io.easymocap_fits import read_easymocap_smpl_dir

    d = tmp_path / "smpl"
    d.mkdir()
    good = {"id": 0, "Rh": [[0, 0, 0]], "Th": [[0, 0, 0]], "poses": [[0.0] * 72], "shapes": [[0.0] * 10]}
    (d / "000000.json").write_text(json.dumps([dict(good, Rh=[[0, float("nan"), 0]])]).replace("NaN", "NaN"))
    with pytest.raises(InputError, match="NaN or inf"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text(json.dumps([dict(good, Th=[[0, 0]])]))
    with pytest.raises(InputError, match="shape"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text(json.dumps([dict(good, poses=[[0.0] * 87])]))
    with pytest.raises(InputError, match="only SMPL"):
        read_easymocap_smpl_dir(d)
    (d / "000000.json").write_text("{not json")
    with pytest.raises(InputError, match="000000.json"):
        read_easymocap_smpl_dir(d)


# ---- THuman4.0 (SMPL-X) ----------------------------------------------------------------------------------------
def test_thuman4_reader_and_ingest(tmp_path):
    from avatarctl.body.smpl import SmplBody

    model = write_random_smpl_npz(tmp_path / "SMPLX_NEUTRAL.npz", "smplx", seed=4)
    body = SmplBody.from_file(model, kind="smplx")
    cap = tmp_path / "th4"
    cams = [Camera(name=f"cam{i:02d}", K=c.K, R=c.R, T=c.T, width=c.width, height=c.height)  # no distortion
            for i, c in enumerate(ring_cameras(3, SIZE, dist=(0, 0, 0, 0, 0)))]
    rng = np.random.default_rng(8)
    n = 4
    arrays = {"global_orient": rng.normal(0, 0.5, (n, 3)), "transl": rng.normal(0, 0.05, (n, 3)),
              "body_pose": rng.normal(0, 0.2, (n, 63)), "betas": rng.normal(0, 1, (1, 10)),
              "jaw_pose": rng.normal(0, 0.1, (n, 3)), "expression": rng.normal(0, 0.5, (n, 10)),
              "left_hand_pose": rng.normal(0, 0.2, (n, 45)), "right_hand_pose": rng.normal(0, 0.2, (n, 45))}
    np.savez(cap / "smpl_params.npz" if cap.mkdir() is None else None, **arrays)
    motion = BodyMotion(body_model="smplx", frame_index=np.arange(n), betas=arrays["betas"][0],
                        **{k: v for k, v in arrays.items() if k != "betas"})
    verts = body.pose(motion).vertices.numpy()
    write_frames(cams, verts, body.faces.numpy(), lambda c, f: cap / "images" / c.name / f"{f:08d}.jpg",
                 lambda c, f: cap / "masks" / c.name / f"{f:08d}.jpg")
    calib = {c.name: {"K": c.K.ravel().tolist(), "R": c.R.ravel().tolist(), "T": c.T.tolist(),
                      "imgSize": [c.width, c.height]} for c in cams}
    (cap / "calibration.json").write_text(json.dumps(calib))
    (cap / "images" / "cam01" / "00000002.jpg").unlink()
    (cap / "missing_img_files.txt").write_text("cam01/00000002.jpg\n")
    res = ingest(cap, tmp_path / "proj", body_model_path=model)
    assert res.format == "thuman4" and res.body_model == "smplx"
    assert res.frames == [0, 1, 3]  # the frame missing in one camera is left out of all
    assert res.vertices_inside_masks > 0.99, res.vertices_inside_masks


# ---- PeopleSnapshot (monocular) ----------------------------------------------------------------------------------
@pytest.mark.parametrize("frames_from", ["images", "video"])
def test_peoplesnapshot_reader_and_ingest(smpl, tmp_path, frames_from):
    import h5py

    path, body = smpl
    cap = tmp_path / "ps"
    cap.mkdir()
    cam = ring_cameras(1, SIZE, dist=(-0.05, 0.01, 0.001, -0.001, 0.0))[0]
    cam = Camera(name="cam0", K=cam.K, R=cam.R, T=cam.T, width=SIZE, height=SIZE, dist=cam.dist)
    rng = np.random.default_rng(9)
    n, extra = 3, 2
    pose = rng.normal(0, 0.2, (n + extra, 72))
    trans = rng.normal(0, 0.05, (n + extra, 3))
    trans[:extra] += 0.5  # leading rows that do not belong to the masked frames
    betas = rng.normal(0, 1, 10)
    motion = BodyMotion(body_model="smpl", frame_index=np.arange(n), global_orient=pose[extra:, :3],
                        body_pose=pose[extra:, 3:], transl=trans[extra:], betas=betas)
    verts = body.pose(motion).vertices.numpy()
    masks, frames = [], []
    bg = plate(cam, 0)
    for f in range(n):
        rgb, sil = render(cam, verts[f], body.faces.numpy(), bg)
        frames.append(rgb)
        masks.append(sil.astype(np.uint8))
    if frames_from == "images":
        (cap / "images").mkdir()
        for f, rgb in enumerate(frames):
            cv2.imwrite(str(cap / "images" / f"{f:06d}.png"), rgb[..., ::-1])
    else:
        video = cv2.VideoWriter(str(cap / "subject.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30, (SIZE, SIZE))
        for rgb in frames:
            video.write(np.ascontiguousarray(rgb[..., ::-1]))
        video.release()
    with h5py.File(cap / "masks.hdf5", "w") as h:
        h["masks"] = np.stack(masks)
    with h5py.File(cap / "reconstructed_poses.hdf5", "w") as h:
        h["pose"], h["trans"], h["betas"] = pose, trans, betas
    with open(cap / "camera.pkl", "wb") as fh:
        pickle.dump({"camera_f": np.array([cam.K[0, 0], cam.K[1, 1]]), "camera_c": cam.K[:2, 2],
                     "camera_k": cam.dist, "camera_rt": cv2.Rodrigues(cam.R)[0].ravel(), "camera_t": cam.T,
                     "width": SIZE, "height": SIZE}, fh, protocol=2)
    res = ingest(cap, tmp_path / "proj", body_model_path=path)
    assert res.format == "peoplesnapshot" and res.cameras == ["cam0"] and res.frames == [0, 1, 2]
    assert res.vertices_inside_masks > 0.99, res.vertices_inside_masks  # the last N poses were used
    from avatarctl.io.project_io import read_frame
    from avatarctl.project import Project

    got = read_frame(Project.open(tmp_path / "proj"), "cam0", 2).astype(float)
    err = [np.abs(got - cv2.undistort(frames[f], cam.K, cam.dist, None, cam.K)).mean() for f in range(n)]
    assert err[2] < 8 and err[2] < 0.5 * min(err[0], err[1]), err  # the right frame (lossy mp4v / JPEG)


# ---- COLMAP ------------------------------------------------------------------------------------------------------
def test_colmap_reader_and_ingest(smpl, tmp_path):
    import pycolmap

    from avatarctl.io.colmap import read_colmap_cameras

    path, body = smpl
    cap = tmp_path / "colmap"
    cams = ring_cameras(2, SIZE, dist=(-0.05, 0.01, 0.001, 0.0005, 0.0))
    rec = pycolmap.Reconstruction()
    for i, c in enumerate(cams):
        cc = pycolmap.Camera.create_from_model_name(i + 1, "OPENCV", 100.0, c.width, c.height)
        cc.params = [c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5, *c.dist[:4]]  # COLMAP pixel centres
        rec.add_camera_with_trivial_rig(cc)
        img = pycolmap.Image(name=f"{c.name}/000000.jpg", camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.T))
    (cap / "sparse" / "0").mkdir(parents=True)
    rec.write(str(cap / "sparse" / "0"))
    got = read_colmap_cameras(cap / "sparse" / "0")
    for g, c in zip(got, cams):
        np.testing.assert_allclose(g.K, c.K, atol=1e-9)
        np.testing.assert_allclose(g.R, c.R, atol=1e-9)
        np.testing.assert_allclose(g.dist, c.dist, atol=1e-12)
    Rh, Th, poses, shapes = random_rhth(2, seed=11)
    motion = BodyMotion(body_model="smpl", frame_index=np.arange(2), global_orient=rng_rot(2), body_pose=poses[:, 3:],
                        transl=Th, betas=shapes)
    motion.save(cap / "motion.npz")
    verts = body.pose(motion).vertices.numpy()
    write_frames(cams, verts, body.faces.numpy(), lambda c, f: cap / "images" / c.name / f"{f:06d}.jpg",
                 lambda c, f: cap / "masks" / c.name / f"{f:06d}.png")
    res = ingest(cap, tmp_path / "proj", body_model_path=path)
    assert res.format == "colmap" and res.vertices_inside_masks > 0.99, res.vertices_inside_masks


def rng_rot(n: int) -> np.ndarray:
    return np.random.default_rng(12).normal(0, 0.5, (n, 3))


# ---- detection -------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("files,fmt", [
    (["annots.npy"], "zju"), (["calibration.json"], "thuman4"), (["camera.pkl", "masks.hdf5"], "peoplesnapshot"),
    (["intri.yml", "extri.yml"], "easymocap"), (["sparse/0/cameras.bin"], "colmap"), (["cameras.txt"], "colmap")])
def test_detect_format(tmp_path, files, fmt):
    from avatarctl.io.detect import detect_format

    for f in files:
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / f).write_bytes(b"")
    got, reason = detect_format(tmp_path)
    assert got == fmt and files[0].split("/")[-1] in reason


def test_detect_unknown_format(tmp_path):
    from avatarctl.io.detect import detect_format

    (tmp_path / "intri.yml").write_text("x")  # half an EasyMocap calibration is not a format
    with pytest.raises(InputError, match="unknown capture format"):
        detect_format(tmp_path)


def test_a_motion_is_read_by_frame_numbers_not_rows():
    """`BodyMotion.for_frames`: the rows of capture frame numbers, in the order asked (a motion whose frames do not
    start at 0 is where `select`, which takes rows, would be wrong); a frame without a fit is named."""
    transl = np.arange(9, dtype=np.float64).reshape(3, 3)
    motion = BodyMotion(body_model="smpl", frame_index=np.array([10, 12, 14]), global_orient=np.zeros((3, 3)),
                        body_pose=np.zeros((3, 69)), transl=transl, betas=np.zeros(10))
    two = motion.for_frames([14, 10])
    assert two.frame_index.tolist() == [14, 10] and np.array_equal(two.transl, transl[[2, 0]])
    with pytest.raises(KeyError, match="frame 11 has no body fit"):
        motion.for_frames([11])

"""Plans and landmarks from ITK / 3D Slicer files: frames (LPS, RAS, patient), the ITK
resampling direction, round trips, and refusals."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pvcmf import cli
from pvcmf.io import (read_itk_transform, read_landmarks, read_plan_file, read_transform,
                      write_itk_transform, write_landmarks)
from pvcmf.io.transforms import check_rigid

HEADER = "#Insight Transform File V1.0\n#Transform 0\n"


def _tfm(tmp_path, name, kind, params, fixed="0 0 0"):
    path = tmp_path / name
    path.write_text(f"{HEADER}Transform: {kind}\nParameters: {params}\nFixedParameters: {fixed}\n")
    return path


def _apply(m, p):
    return (m @ np.append(p, 1.0))[:3]


def test_slicer_translation_file(tmp_path):
    """Slicer moves the maxilla 5 mm anterior and 2 mm up (RAS (0, 5, 2)); it saves the ITK
    resampling transform, i.e. the inverse move in LPS: translation (0, 5, -2)."""
    path = _tfm(tmp_path, "maxilla.tfm", "AffineTransform_double_3_3",
                "1 0 0 0 1 0 0 0 1 0 5 -2")
    m = read_transform(path)
    assert np.allclose(m[:3, :3], np.eye(3))
    assert np.allclose(m[:3, 3], [0.0, 5.0, 2.0])  # patient: y anterior, z superior
    # the file as ITK applies it (fixed -> moving, LPS)
    assert np.allclose(read_itk_transform(path)[:3, 3], [0.0, 5.0, -2.0])
    # a file that already holds the move, given in RAS
    m2 = read_transform(path, itk_direction="moving", frame="RAS")
    assert np.allclose(m2[:3, 3], [0.0, 5.0, -2.0])


def test_euler_about_a_centre_lps(tmp_path):
    """ITK Euler3D (ZXY) about a centre, LPS: the bone move is the inverse, and the LPS ->
    patient flip of y reverses the sense of a rotation about z."""
    theta, c_lps = math.radians(10.0), [5.0, -40.0, 12.0]
    path = _tfm(tmp_path, "mandible.tfm", "Euler3DTransform_double_3_3",
                f"0 0 {theta!r} 0 0 0", fixed=" ".join(map(repr, c_lps)))
    m = read_transform(path)
    c = np.array([5.0, 40.0, 12.0])  # the centre in the patient frame
    x = np.array([20.0, 60.0, -3.0])
    d = x - c
    rot = np.array([[math.cos(theta), -math.sin(theta), 0],
                    [math.sin(theta), math.cos(theta), 0], [0, 0, 1]])
    assert np.allclose(_apply(m, x), c + rot @ d)
    # the same rotation as a versor and as a composite of two half rotations
    s = math.sin(theta / 2)
    vpath = _tfm(tmp_path, "v.tfm", "VersorRigid3DTransform_double_3_3", f"0 0 {s!r} 0 0 0",
                 fixed=" ".join(map(repr, c_lps)))
    assert np.allclose(read_transform(vpath), m)
    half = f"Transform: Euler3DTransform_double_3_3\nParameters: 0 0 {theta / 2!r} 0 0 0\n" \
           f"FixedParameters: {' '.join(map(repr, c_lps))}\n"
    comp = tmp_path / "composite.tfm"
    comp.write_text(f"{HEADER}Transform: CompositeTransform_double_3_3\n#Transform 1\n{half}"
                    f"#Transform 2\n{half}")
    assert np.allclose(read_transform(comp), m)


def test_euler_zxy_order(tmp_path):
    """ITK's default Euler order is R = Rz Rx Ry (ComputeZYX off), Rz Ry Rx with the flag."""
    a, b, g = 0.1, -0.2, 0.3
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(g), -math.sin(g), 0], [math.sin(g), math.cos(g), 0], [0, 0, 1]])
    p = _tfm(tmp_path, "e.tfm", "Euler3DTransform_double_3_3", f"{a} {b} {g} 1 2 3")
    assert np.allclose(read_itk_transform(p)[:3, :3], rz @ rx @ ry)
    p = _tfm(tmp_path, "e2.tfm", "Euler3DTransform_double_3_3", f"{a} {b} {g} 1 2 3",
             fixed="0 0 0 1")
    assert np.allclose(read_itk_transform(p)[:3, :3], rz @ ry @ rx)


@pytest.mark.parametrize("frame", ["patient", "LPS", "RAS"])
def test_itk_round_trip(tmp_path, frame):
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", [3.0, -7.0, 11.0], degrees=True).as_matrix()
    m[:3, 3] = [1.5, -2.0, 4.0]
    path = write_itk_transform(m, tmp_path / "t.tfm", frame=frame)
    assert path.read_text().startswith("#Insight Transform File V1.0")
    back = read_transform(path)  # patient frame
    F = {"patient": np.eye(4), "LPS": np.diag([1.0, -1, 1, 1]), "RAS": np.diag([-1.0, 1, 1, 1])}
    assert np.allclose(back, F[frame] @ m @ F[frame], atol=1e-12)


def test_refuses_bad_transforms(tmp_path):
    scaled = _tfm(tmp_path, "s.tfm", "AffineTransform_double_3_3", "1.1 0 0 0 1 0 0 0 1 0 0 0")
    with pytest.raises(ValueError, match="not rigid"):
        read_transform(scaled)
    mirror = _tfm(tmp_path, "m.tfm", "AffineTransform_double_3_3", "-1 0 0 0 1 0 0 0 1 0 0 0")
    with pytest.raises(ValueError, match="not rigid"):
        read_transform(mirror)
    sim = _tfm(tmp_path, "sim.tfm", "Similarity3DTransform_double_3_3", "0 0 0 0 0 0 2")
    with pytest.raises(ValueError, match="scale factors"):
        read_transform(sim)
    bspline = _tfm(tmp_path, "b.tfm", "BSplineTransform_double_3_3", "0 0 0")
    with pytest.raises(ValueError, match="not supported"):
        read_transform(bspline)
    short = _tfm(tmp_path, "p.tfm", "AffineTransform_double_3_3", "1 0 0")
    with pytest.raises(ValueError, match="needs 12 parameters"):
        read_transform(short)
    (tmp_path / "x.tfm").write_text("hello\n")
    with pytest.raises(ValueError, match="not an ITK transform"):
        read_transform(tmp_path / "x.tfm")
    with pytest.raises(ValueError, match="unknown extension"):
        read_transform(tmp_path / "t.nrrd")
    with pytest.raises(ValueError, match="not rigid"):
        check_rigid(np.diag([1.0, 1.0, 2.0, 1.0]))


def test_hdf5_needs_h5py(tmp_path):
    try:
        import h5py  # noqa: F401
    except ModuleNotFoundError:
        (tmp_path / "t.h5").write_bytes(b"\x89HDF\r\n")
        with pytest.raises(ModuleNotFoundError, match="needs h5py"):
            read_transform(tmp_path / "t.h5")
    else:
        pytest.skip("h5py is installed: the HDF5 path is exercised by ITK files, not here")


def test_plan_file_of_transforms(tmp_path):
    _tfm(tmp_path, "maxilla.tfm", "AffineTransform_double_3_3", "1 0 0 0 1 0 0 0 1 0 5 -2")
    plan = tmp_path / "plan.toml"
    plan.write_text('name = "from slicer"\n\n[[osteotomy]]\nsegment = "maxilla"\n'
                    'transform = "maxilla.tfm"\n\n[[osteotomy]]\nsegment = "mandible"\n'
                    'frame = "RAS"\nmatrix = [[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], '
                    '[0, 0, 0, 1]]\n')
    p = read_plan_file(plan)
    assert p.name == "from slicer" and p.segments == ("maxilla", "mandible")
    maxilla, mandible = p.osteotomies
    assert np.allclose(maxilla.translation, (0.0, 2.0, 5.0))  # (horizontal, vertical, AP)
    assert np.allclose(maxilla.matrix(centroid=(9.0, 9.0, 9.0))[:3, 3], [0.0, 5.0, 2.0])
    assert np.allclose(mandible.matrix()[:3, 3], [-1.0, 2.0, 3.0])
    # JSON, patient frame, a rotation: the plan's own matrix() gives it back
    from scipy.spatial.transform import Rotation

    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec([0.05, -0.1, 0.02]).as_matrix()
    m[:3, 3] = [0.5, 3.0, -1.0]
    js = tmp_path / "plan.json"
    js.write_text(json.dumps({"osteotomy": [{"segment": "mandible", "matrix": m.tolist()}]}))
    assert np.allclose(read_plan_file(js).osteotomies[0].matrix(), m, atol=1e-12)
    # a plain plan still reads
    plain = tmp_path / "plain.toml"
    plain.write_text('[[osteotomy]]\nsegment = "maxilla"\ntranslation = [1.0, 2.0, 3.0]\n')
    assert read_plan_file(plain).osteotomies[0].translation == (1.0, 2.0, 3.0)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"osteotomy": [{"segment": "maxilla",
                                              "matrix": np.diag([2.0, 1, 1, 1]).tolist()}]}))
    with pytest.raises(ValueError, match="rigid"):
        read_plan_file(bad)
    both = tmp_path / "both.json"
    both.write_text(json.dumps({"osteotomy": [{"segment": "maxilla", "matrix": np.eye(4).tolist(),
                                               "translation": [1, 0, 0]}]}))
    with pytest.raises(ValueError, match="one or the other"):
        read_plan_file(both)


# --------------------------------------------------------------------------- landmarks
MRK = {  # Slicer 5 markups JSON, as the Markups module writes it (trimmed display section)
    "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
               "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
    "markups": [{
        "type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm",
        "locked": False, "fixedNumberOfControlPoints": False, "labelFormat": "%N-%d",
        "lastUsedControlPointNumber": 3,
        "controlPoints": [
            {"id": "1", "label": "nasion", "description": "", "associatedNodeID": "",
             "position": [10.0, 20.0, 30.0], "orientation": [-1.0, -0.0, -0.0, -0.0, -1.0,
                                                            -0.0, 0.0, 0.0, 1.0],
             "selected": True, "locked": False, "visibility": True,
             "positionStatus": "defined"},
            {"id": "2", "label": "pogonion", "position": [-3.5, -80.25, -60.0],
             "positionStatus": "defined"},
            {"id": "3", "label": "unplaced", "position": [0.0, 0.0, 0.0],
             "positionStatus": "undefined"},
        ],
        "measurements": [],
        "display": {"visibility": True, "opacity": 1.0, "glyphScale": 3.0},
    }],
}
EXPECTED = {"nasion": [10.0, -20.0, 30.0], "pogonion": [-3.5, 80.25, -60.0]}  # patient


def test_mrk_json_lps_and_ras(tmp_path):
    lps = tmp_path / "lm.mrk.json"
    lps.write_text(json.dumps(MRK))
    got = read_landmarks(lps)
    assert list(got) == ["nasion", "pogonion"]  # undefined points skipped
    for name, want in EXPECTED.items():
        assert np.allclose(got[name], want)
    ras = json.loads(json.dumps(MRK))
    ras["markups"][0]["coordinateSystem"] = "RAS"
    for point in ras["markups"][0]["controlPoints"]:  # the same physical points in RAS
        x, y, z = point["position"]
        point["position"] = [-x, -y, z]
    (tmp_path / "ras.mrk.json").write_text(json.dumps(ras))
    got_ras = read_landmarks(tmp_path / "ras.mrk.json")
    for name, want in EXPECTED.items():
        assert np.allclose(got_ras[name], want)
    assert np.allclose(read_landmarks(lps, frame="RAS")["nasion"], [-10.0, -20.0, 30.0])


def test_fcsv(tmp_path):
    path = tmp_path / "lm.fcsv"
    path.write_text("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
                    "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,"
                    "associatedNodeID\n"
                    "1,10,20,30,0,0,0,1,1,1,0,nasion,,\n"
                    "2,-3.5,-80.25,-60,0,0,0,1,1,1,0,pogonion,\"chin, soft\",\n")
    got = read_landmarks(path)
    for name, want in EXPECTED.items():
        assert np.allclose(got[name], want)
    old = tmp_path / "old.fcsv"  # Slicer 4.x: numeric system, 0 = RAS
    old.write_text("# Markups fiducial file version = 4.6\n# CoordinateSystem = 0\n"
                   "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                   "vtkMRMLMarkupsFiducialNode_0,-10,-20,30,0,0,0,1,1,1,0,nasion,,\n")
    assert np.allclose(read_landmarks(old)["nasion"], EXPECTED["nasion"])


@pytest.mark.parametrize("name", ["out.mrk.json", "out.fcsv"])
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_landmark_round_trip(tmp_path, name, system):
    lm = {k: np.array(v) for k, v in EXPECTED.items()}
    path = write_landmarks(lm, tmp_path / name, coordinate_system=system)
    assert system in path.read_text()
    back = read_landmarks(path)
    assert list(back) == list(lm)
    for k in lm:
        assert np.array_equal(back[k], lm[k])


def test_refuses_bad_landmark_files(tmp_path):
    empty = json.loads(json.dumps(MRK))
    empty["markups"][0]["controlPoints"] = []
    (tmp_path / "empty.mrk.json").write_text(json.dumps(empty))
    with pytest.raises(ValueError, match="no landmark points"):
        read_landmarks(tmp_path / "empty.mrk.json")
    (tmp_path / "header.fcsv").write_text("# CoordinateSystem = LPS\n")
    with pytest.raises(ValueError, match="no landmark points"):
        read_landmarks(tmp_path / "header.fcsv")
    ijk = json.loads(json.dumps(MRK))
    ijk["markups"][0]["coordinateSystem"] = "IJK"
    (tmp_path / "ijk.mrk.json").write_text(json.dumps(ijk))
    with pytest.raises(ValueError, match="coordinateSystem"):
        read_landmarks(tmp_path / "ijk.mrk.json")
    dup = json.loads(json.dumps(MRK))
    dup["markups"][0]["controlPoints"][1]["label"] = "nasion"
    (tmp_path / "dup.mrk.json").write_text(json.dumps(dup))
    with pytest.raises(ValueError, match="more than once"):
        read_landmarks(tmp_path / "dup.mrk.json")
    (tmp_path / "lm.csv").write_text("a,1,2,3\n")
    with pytest.raises(ValueError, match="unknown extension"):
        read_landmarks(tmp_path / "lm.csv")
    (tmp_path / "nan.fcsv").write_text("1,nan,2,3,0,0,0,1,1,1,0,nasion,,\n")
    with pytest.raises(ValueError, match="not finite"):
        read_landmarks(tmp_path / "nan.fcsv")


def test_cli_takes_landmarks_export_and_transform_plans(tmp_path, capsys):
    args = cli.build_parser().parse_args(
        ["simulate", "--ct", "x", "--plan", "p.toml", "--out", "o", "--landmarks", "lm.fcsv",
         "--export", "model.inp"])
    assert str(args.landmarks) == "lm.fcsv" and str(args.export) == "model.inp"
    plan = tmp_path / "plan.toml"
    plan.write_text('[[osteotomy]]\nsegment = "maxilla"\ntransform = "missing.tfm"\n')
    assert cli.main(["simulate", "--ct", "x", "--plan", str(plan), "--out",
                     str(tmp_path / "o")]) == 2  # refused before any CT is read
    assert "missing.tfm" in capsys.readouterr().err
    empty = tmp_path / "lm.mrk.json"
    empty.write_text(json.dumps({"markups": [{"coordinateSystem": "LPS", "controlPoints": []}]}))
    good = tmp_path / "good.toml"
    good.write_text('[[osteotomy]]\nsegment = "maxilla"\ntranslation = [0.0, 0.0, 2.0]\n')
    assert cli.main(["simulate", "--ct", "x", "--plan", str(good), "--landmarks", str(empty),
                     "--out", str(tmp_path / "o")]) == 2
    assert "no landmark points" in capsys.readouterr().err


@pytest.mark.parametrize("kind", ["euler", "affine", "composite"])
def test_hdf5_transform_written_by_simpleitk(tmp_path, kind):
    """An ITK HDF5 transform written by SimpleITK (ITK's own writer) reads as the same matrix
    as the ITK text file SimpleITK writes for it."""
    pytest.importorskip("h5py", reason="the ITK HDF5 reader needs h5py (test extra)")
    sitk = pytest.importorskip("SimpleITK")
    euler = sitk.Euler3DTransform((1.0, -2.0, 3.0), 0.1, -0.2, 0.3, (4.0, 5.0, -6.0))
    if kind == "euler":
        t = euler
    elif kind == "affine":
        t = sitk.AffineTransform(euler.GetMatrix(), euler.GetTranslation(), euler.GetCenter())
    else:
        t = sitk.CompositeTransform([euler, sitk.TranslationTransform(3, (0.5, 0.0, -1.5))])
    sitk.WriteTransform(t, str(tmp_path / "t.h5"))
    sitk.WriteTransform(t, str(tmp_path / "t.tfm"))
    from_h5 = read_itk_transform(tmp_path / "t.h5")
    np.testing.assert_allclose(from_h5, read_itk_transform(tmp_path / "t.tfm"), atol=1e-9)
    point = np.array([10.0, -20.0, 30.0])  # ITK maps fixed -> moving points
    np.testing.assert_allclose(from_h5[:3, :3] @ point + from_h5[:3, 3],
                               t.TransformPoint(point.tolist()), atol=1e-9)


def test_plan_file_errors_name_the_file_and_the_keys(tmp_path):
    """A missing plan names itself; a misspelt key lists every key a plan file takes,
    'transform' and 'frame' included."""
    from pvcmf.io import read_plan_file

    with pytest.raises(FileNotFoundError, match=r"plan file .*nope\.toml.* does not exist"):
        read_plan_file(tmp_path / "nope.toml")
    folder = tmp_path / "folder.toml"
    folder.mkdir()
    with pytest.raises(FileNotFoundError, match="is a folder"):
        read_plan_file(folder)
    plan = tmp_path / "plan.toml"
    plan.write_text('[[osteotomy]]\nsegment = "mandible"\ntransfrom = "m.tfm"\n')
    with pytest.raises(ValueError, match=r"\['transfrom'\].*'transform', 'frame'"):
        read_plan_file(plan)

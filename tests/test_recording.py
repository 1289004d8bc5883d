"""The Rerun recorder: what a person opening the file will find."""

import numpy as np
from rrd_util import pinhole_K, rrd_column, rrd_rows

from calib.camera import make_T, rotation_from_normal
from turntable.recording import Recorder


def test_cameras_images_and_meshes_are_recorded(tmp_path):
    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 159.5], [0, 800.0, 119.5], [0, 0, 1]])
    p = tmp_path / "r.rrd"
    with Recorder(p) as rec:
        rec.log_target(80, 50)
        for i in range(3):
            T = make_T(rotation_from_normal([0, -0.8, -0.6]), [0, 20, 450])
            rec.log_camera(i, K, 320, 240, T, image_rgb=rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
            rec.log_silhouette(i, np.pad(np.ones((100, 100), bool), 70)[:240, :320])
        V = rng.normal(size=(4, 3))
        rec.log_mesh("mesh", V, [[0, 1, 2], [0, 2, 3]], normals=V, colors_rgb=np.full((4, 3), 200, np.uint8))
    rows = rrd_rows(p)
    assert rows["/world/camera"]["Pinhole:image_from_camera"] == 3
    assert rows["/world/camera/image"]["EncodedImage:blob"] == 3
    assert rows["/world/mesh"]["Mesh3D:vertex_colors"] == 1
    assert "LineStrips3D:strips" in rows["/world/target"]
    # our pixel-centre principal point is shifted by half a pixel into Rerun's corner convention
    K_rr = pinhole_K(rrd_column(p, "/world/camera", "Pinhole:image_from_camera")[0])
    np.testing.assert_allclose(K_rr[:2, 2], K[:2, 2] + 0.5)
    assert K_rr[0, 0] == 800.0

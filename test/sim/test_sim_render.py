"""The frame simulator: ground truth, rolling-shutter stripes, optics and sensor effects."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from vlp_ros.beacon.encoding import packet_waveform, tone_waveform
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.ellipse import fit_ellipse, geometric_distances
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.sim.coverage import Circle, disc_coverage, plane_points
from vlp_ros.sim.render import crop_camera, lamp_roi, render_frame, SimLamp
from vlp_ros.sim.sensor import SensorModel

WHITE = (1.0, 1.0, 1.0)
DISTORTION = np.array([-0.12, 0.03, 0.001, -0.0005, 0.0])


def small_camera(D=None) -> CameraModel:
    K = np.array([[600.0, 0.0, 161.3], [0.0, 600.0, 118.7], [0.0, 0.0, 1.0]])
    return CameraModel(320, 240, K, np.zeros(5) if D is None else D)


def tilted_pose(degrees=12.0, yaw=35.0) -> Pose:
    rotation = Rotation.from_euler('zx', [yaw, degrees], degrees=True).as_matrix()
    return Pose(rotation, [0.02, -0.03, 0.0])


def in_view(pose: Pose, direction=(0.05, -0.03), height=1.0) -> tuple[float, float]:
    """Map (x, y) at ``height`` seen along camera direction (x/z, y/z)."""
    ray = pose.rotation @ np.array([direction[0], direction[1], 1.0])
    point = pose.position + (height - pose.position[2]) / ray[2] * ray
    return point[0], point[1]


def make_lamp(lamp_id=9, xy=(0.05, 0.15), height=1.0, radius=0.1, marker_angle=np.pi, depth=0.0,
              **light) -> SimLamp:
    lamp = Lamp(f'lamp{lamp_id}', lamp_id, [xy[0], xy[1], height], radius,
                marker_angle=marker_angle, marker_distance=0.85 * radius)
    return SimLamp(lamp, packet_waveform(lamp_id, 4000.0, depth, offset=1.3e-4), **light)


def quiet_sensor(**changes) -> SensorModel:
    settings = {'row_time': 3e-5, 'exposure': 2e-5, 'ambient_bgr': (0.0, 0.0, 0.0), 'blur_sigma': 0.0}
    settings.update(changes)
    return SensorModel(**settings)


def test_truth_is_the_camera_projection_of_marker_and_rim():
    pose = tilted_pose()
    camera, sim = small_camera(DISTORTION), make_lamp(xy=in_view(pose))
    frame = render_frame(camera, pose, [sim], quiet_sensor(), 0.0, None)
    truth = frame.truth(sim.lamp.id)
    assert truth.visible and truth.fully_inside
    expected_marker = camera.project(pose.map_to_camera(sim.lamp.marker_position()))[0]
    np.testing.assert_allclose(truth.marker_pixel, expected_marker, atol=1e-6)  # a micro-pixel
    rim = camera.project(pose.map_to_camera(sim.lamp.rim_points(90)))
    np.testing.assert_allclose(truth.rim_pixels[::2], rim, atol=1e-6)
    np.testing.assert_allclose(truth.ellipse, fit_ellipse(camera.undistort_pixels(rim)), atol=1e-6)


def test_disc_area_and_centroid_match_the_true_ellipse():
    camera, pose = small_camera(), tilted_pose(degrees=20.0)
    sim = make_lamp(xy=in_view(pose), peak_dn=200.0, color_bgr=WHITE, marker_bgr=WHITE)
    frame = render_frame(camera, pose, [sim], quiet_sensor(), 0.0, None)
    cx, cy, a, b, _ = frame.truth(sim.lamp.id).ellipse
    weight = frame.image[..., 1].astype(float) / 200.0
    ys, xs = np.mgrid[:camera.height, :camera.width]
    assert weight.sum() == pytest.approx(np.pi * a * b, rel=2e-4)
    # The image of a disc is the interior of the projected rim ellipse, whose centroid is its centre.
    assert (weight * xs).sum() / weight.sum() == pytest.approx(cx, abs=0.01)
    assert (weight * ys).sum() / weight.sum() == pytest.approx(cy, abs=0.01)


@pytest.mark.parametrize('radius', [0.1, 0.01])
def test_edge_coverage_matches_dense_sampling(radius):
    camera, pose = small_camera(DISTORTION), tilted_pose(degrees=25.0)
    x, y = in_view(pose, (0.08, 0.05))
    circle = Circle(np.array([x, y]), radius)
    centre = camera.project(pose.map_to_camera([x, y, 1.0]))[0].astype(int)
    half = int(900 * radius) + 3
    bbox = (centre[0] - half, centre[1] - half, centre[0] + half, centre[1] + half)
    coverage = disc_coverage(camera, pose, 1.0, [circle], bbox)[0]
    ys, xs = np.mgrid[bbox[1]:bbox[3], bbox[0]:bbox[2]]
    # Dense 20 x 20 sampling of every pixel that is not plainly inside or outside.
    dense = coverage.astype(float)
    centres = plane_points(camera, pose, np.stack([xs.ravel(), ys.ravel()], axis=1), 1.0)
    near = np.abs(np.linalg.norm(centres - circle.center_xy, axis=1) - radius).reshape(xs.shape) < 3.0 / 600.0
    offsets = (np.arange(20) + 0.5) / 20 - 0.5
    ox, oy = (v.ravel() for v in np.meshgrid(offsets, offsets))
    samples = np.stack([(xs[near][:, None] + ox).ravel(), (ys[near][:, None] + oy).ravel()], axis=1)
    inside = np.linalg.norm(plane_points(camera, pose, samples, 1.0) - circle.center_xy, axis=1) < radius
    dense[near] = inside.reshape(-1, ox.size).mean(axis=1)
    assert np.count_nonzero((dense > 0) & (dense < 1)) > 20
    assert np.abs(coverage - dense).max() < 0.04
    for axis in (xs, ys):
        assert (coverage * axis).sum() / coverage.sum() == pytest.approx((dense * axis).sum() / dense.sum(), abs=0.01)


def test_distortion_moves_the_disc_where_the_model_says():
    camera, pose = small_camera(DISTORTION), tilted_pose(degrees=18.0)
    sim = make_lamp(xy=in_view(pose, (0.12, 0.08)), peak_dn=200.0, color_bgr=WHITE, marker_bgr=WHITE)
    distorted = render_frame(camera, pose, [sim], quiet_sensor(), 0.0, None)
    ideal = render_frame(small_camera(), pose, [sim], quiet_sensor(), 0.0, None)
    ellipse = distorted.truth(sim.lamp.id).ellipse
    ys, xs = np.mgrid[:camera.height, :camera.width]
    pixels = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    distance = geometric_distances(ellipse, camera.undistort_pixels(pixels)).reshape(xs.shape)
    green = distorted.image[..., 1]
    assert np.all(green[distance < -1.0] == 200) and np.all(green[distance > 1.0] == 0)
    assert np.count_nonzero(distorted.image != ideal.image) > 500


def test_stripes_follow_the_waveform_row_by_row():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    sim = make_lamp(xy=(0.0, 0.0), depth=0.6, peak_dn=200.0, color_bgr=WHITE)
    sensor = quiet_sensor()
    frame = render_frame(camera, pose, [sim], sensor, 0.37e-3, None)
    cx, cy, _, b, _ = frame.truth(sim.lamp.id).ellipse
    rows = np.arange(int(cy - b) + 2, int(cy + b) - 1)
    expected = 200.0 * sim.waveform.mean_brightness(0.37e-3 + rows * sensor.row_time, sensor.exposure)
    measured = frame.image[rows, int(round(cx)), 1].astype(float)
    assert np.ptp(expected) > 70.0
    np.testing.assert_allclose(measured, expected, atol=0.51)


def test_full_depth_gives_fully_dark_stripes():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    sim = make_lamp(xy=(0.0, 0.0), depth=1.0, peak_dn=180.0)
    sensor = quiet_sensor(ambient_bgr=(20.0, 20.0, 20.0), exposure=1e-6)
    frame = render_frame(camera, pose, [sim], sensor, 0.0, np.random.default_rng(3))
    cx, cy, _, b, _ = frame.truth(sim.lamp.id).ellipse
    rows = np.arange(int(cy - b) + 2, int(cy + b) - 1)
    level = sim.waveform.mean_brightness(rows * sensor.row_time, sensor.exposure)
    dark, lit = rows[level < 1e-9], rows[level > 1.0 - 1e-9]
    assert dark.size > 10 and lit.size > 10
    columns = slice(int(cx) - 20, int(cx) + 20)
    assert frame.image[dark, columns].mean() < 0.5
    assert frame.image[lit, columns, 1].mean() > 150.0


def test_noise_has_shot_and_read_statistics():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    sensor = quiet_sensor(ambient_bgr=(30.0, 30.0, 30.0), read_noise=8.0)
    sim = make_lamp(xy=(0.0, 0.0), radius=0.12, peak_dn=150.0, color_bgr=WHITE)
    frame = render_frame(camera, pose, [sim], sensor, 0.0, np.random.default_rng(4))
    cx, cy = frame.truth(sim.lamp.id).center_pixel.round().astype(int)
    g = sensor.dn_per_electron
    for level, patch in ((150.0, frame.image[cy - 30:cy + 30, cx - 30:cx + 30, 1]),
                         (30.0, frame.image[:40, :, 1])):
        values = patch.astype(float)
        expected_sigma = np.sqrt(g * level + (g * sensor.read_noise) ** 2 + 1.0 / 12.0)
        assert values.mean() == pytest.approx(level, abs=0.2)
        assert values.std() == pytest.approx(expected_sigma, rel=0.1)


def test_bright_lamps_saturate_at_255_and_at_the_full_well():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    sim = make_lamp(xy=(0.0, 0.0), peak_dn=400.0, color_bgr=WHITE)
    frame = render_frame(camera, pose, [sim], quiet_sensor(), 0.0, np.random.default_rng(5))
    cx, cy = frame.truth(sim.lamp.id).center_pixel.round().astype(int)
    assert np.all(frame.image[cy - 20:cy + 20, cx - 20:cx + 20] == 255)
    small_well = quiet_sensor(full_well=2000.0, gain=0.08, read_noise=0.0)
    frame = render_frame(camera, pose, [sim], small_well, 0.0, np.random.default_rng(5))
    assert np.all(frame.image[cy - 20:cy + 20, cx - 20:cx + 20] == 160)


@pytest.mark.parametrize('pattern', ['rggb', 'bggr', 'grbg', 'gbrg'])
def test_bayer_mosaic_keeps_the_filtered_channel(pattern):
    pose = tilted_pose()
    camera, sim = small_camera(), make_lamp(xy=in_view(pose), depth=0.5)
    colour = render_frame(camera, pose, [sim], quiet_sensor(ambient_bgr=(10.0, 20.0, 30.0)), 0.0, None)
    raw = render_frame(camera, pose, [sim], quiet_sensor(ambient_bgr=(10.0, 20.0, 30.0), bayer=pattern), 0.0, None)
    assert raw.image.shape == (camera.height, camera.width) and raw.encoding == f'bayer_{pattern}8'
    channel = {'b': 0, 'g': 1, 'r': 2}
    for k, letter in enumerate(pattern):
        site = (slice(k // 2, None, 2), slice(k % 2, None, 2))
        np.testing.assert_array_equal(raw.image[site], colour.image[site + (channel[letter],)])


def test_roi_equals_the_crop_of_the_full_frame_and_shifts_the_truth():
    camera, pose = small_camera(DISTORTION), tilted_pose()
    sim = make_lamp(xy=in_view(pose), depth=0.7)
    sensor = quiet_sensor(ambient_bgr=(5.0, 6.0, 7.0), blur_sigma=0.8, bayer='rggb')
    full = render_frame(camera, pose, [sim], sensor, 1e-3, None)
    roi = lamp_roi(camera, pose, sim.lamp, 151)
    x0, y0, w, h = roi
    part = render_frame(camera, pose, [sim], sensor, 1e-3, None, roi=roi)
    np.testing.assert_array_equal(part.image, full.image[y0:y0 + h, x0:x0 + w])
    assert part.start_time == pytest.approx(1e-3 + y0 * sensor.row_time)
    shift = np.array([x0, y0])
    np.testing.assert_allclose(part.truth(sim.lamp.id).marker_pixel + shift, full.truth(sim.lamp.id).marker_pixel)
    np.testing.assert_allclose(part.truth(sim.lamp.id).ellipse[:2] + shift, full.truth(sim.lamp.id).ellipse[:2])
    assert part.camera.K[0, 2] == camera.K[0, 2] - x0


def test_bayer_pattern_follows_an_odd_roi_origin():
    pose = tilted_pose()
    camera, sim = small_camera(), make_lamp(xy=in_view(pose))
    sensor = quiet_sensor(bayer='rggb')
    assert render_frame(camera, pose, [sim], sensor, 0.0, None, roi=(1, 0, 50, 50)).encoding == 'bayer_grbg8'
    assert render_frame(camera, pose, [sim], sensor, 0.0, None, roi=(0, 1, 50, 50)).encoding == 'bayer_gbrg8'
    assert render_frame(camera, pose, [sim], sensor, 0.0, None, roi=(3, 5, 50, 50)).encoding == 'bayer_bggr8'


def test_lamps_out_of_view_are_reported_invisible():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    beside = make_lamp(lamp_id=1, xy=(3.0, 0.0))
    below = make_lamp(lamp_id=2, xy=(0.0, 0.0), height=-1.0)
    in_view = make_lamp(lamp_id=3, xy=(0.0, 0.0))
    frame = render_frame(camera, pose, [beside, below, in_view], quiet_sensor(), 0.0, None)
    assert [t.visible for t in frame.lamps] == [False, False, True]
    assert frame.truth(1).bbox is None and frame.truth(3).bbox is not None


def test_partly_visible_lamp_is_visible_but_not_fully_inside():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    sim = make_lamp(xy=(0.27, 0.0))
    truth = render_frame(camera, pose, [sim], quiet_sensor(), 0.0, None).truth(sim.lamp.id)
    assert truth.visible and not truth.fully_inside


def test_nearer_lamp_occludes_the_farther_one():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    far = make_lamp(lamp_id=1, xy=(0.0, 0.0), height=2.0, radius=0.2, peak_dn=100.0, color_bgr=WHITE)
    near = make_lamp(lamp_id=2, xy=(0.0, 0.0), height=1.0, radius=0.03, peak_dn=200.0, color_bgr=WHITE)
    frame = render_frame(camera, pose, [near, far], quiet_sensor(), 0.0, None)
    cx, cy = frame.truth(2).center_pixel.round().astype(int)
    assert frame.image[cy, cx, 1] == 200 and frame.image[cy, cx + 40, 1] == 100


def test_tone_waveform_renders_periodic_stripes():
    camera, pose = small_camera(), Pose(np.eye(3), [0.0, 0.0, 0.0])
    lamp = Lamp('tone', 1, [0.0, 0.0, 1.0], 0.1, marker_distance=0.085, frequency=1000.0)
    sim = SimLamp(lamp, tone_waveform(1000.0, 1.0), color_bgr=WHITE)
    sensor = quiet_sensor(exposure=1e-6)
    frame = render_frame(camera, pose, [sim], sensor, 0.0, None)
    two_periods = int(round(2e-3 / sensor.row_time))
    column = frame.image[60:100, 160, 1].astype(float)
    shifted = frame.image[60 + two_periods:100 + two_periods, 160, 1]
    assert np.ptp(column) > 150.0
    assert np.mean(np.abs(column - shifted)) < 0.25 * np.mean(np.abs(column - column.mean()))


def test_bad_inputs_are_rejected():
    lamp = Lamp('l', 1, [0.0, 0.0, 1.0], 0.1, marker_distance=0.11)
    with pytest.raises(ValueError, match='outside the rim'):
        SimLamp(lamp, tone_waveform(1000.0, 0.5))
    with pytest.raises(ValueError, match='does not lie on'):
        crop_camera(small_camera(), (300, 0, 50, 50))
    folding = CameraModel(320, 240, small_camera().K, [-2.5, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match='folds back'):
        render_frame(folding, tilted_pose(), [make_lamp()], quiet_sensor(), 0.0, None)
    with pytest.raises(ValueError, match='bayer'):
        quiet_sensor(bayer='rgbg')

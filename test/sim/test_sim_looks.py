"""The looks of real lamps and cameras: each effect renders what it claims, within physical tolerances."""
import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from scipy.integrate import quad
from scipy.special import i0e
from scipy.stats import norm

from vlp_ros.beacon.encoding import packet_waveform, tone_waveform, Waveform
from vlp_ros.benchmarks import look_check
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.pose import Pose
from vlp_ros.images.conversion import decode_compressed
from vlp_ros.images.message import parse_compressed_image
from vlp_ros.sim import __main__ as cli
from vlp_ros.sim.bag_writer import COMPRESSED_TOPIC, JPEG_FORMAT, TYPESTORE
from vlp_ros.sim.looks import apply_look, Look, LOOKS, transported
from vlp_ros.sim.recording import record, write_params
from vlp_ros.sim.render import render_frame, SimLamp
from vlp_ros.sim.scenarios import paper_scenario, robot_tone_scenario, with_rim_markers
from vlp_ros.sim.sensor import SensorModel

import yaml

STEADY = Waveform(np.array([1], dtype=np.uint8), 1.0, 0.0)
WHITE = (1.0, 1.0, 1.0)
LEVEL = 200.0


def camera(width=640, height=480) -> CameraModel:
    return CameraModel(width, height, [[600.0, 0.0, (width - 1) / 2], [0.0, 600.0, (height - 1) / 2], [0.0, 0.0, 1.0]])


def lamp(radius=0.05, waveform=STEADY, marker_distance=0.88, marker_radius=0.09, **light) -> SimLamp:
    """Return a lamp 1 m straight above the camera (image radius 600 * radius px, centred)."""
    geometry = Lamp('l', 3, [0.0, 0.0, 1.0], radius, marker_angle=0.4, marker_distance=marker_distance * radius)
    light.setdefault('color_bgr', WHITE)
    return SimLamp(geometry, waveform, peak_dn=LEVEL, marker_radius=marker_radius * radius, **light)


def sensor(**changes) -> SensorModel:
    settings = {'row_time': 3e-5, 'exposure': 2e-5, 'ambient_bgr': (0.0, 0.0, 0.0), 'blur_sigma': 0.0}
    settings.update(changes)
    return SensorModel(**settings)


UP = Pose(np.eye(3), [0.0, 0.0, 0.0])


def render(sim: SimLamp, sensor_model: SensorModel, cam: CameraModel | None = None) -> np.ndarray:
    return render_frame(cam or camera(), UP, [sim], sensor_model, 0.0, None).image[..., 1].astype(float)


def blurred_disc(d: float, radius: float, sigma: float) -> float:
    """Return a uniform disc of ``radius`` blurred by an isotropic Gaussian, at distance ``d`` from its centre."""
    # Integrand rho/s^2 exp(-(rho^2 + d^2) / 2 s^2) I0(rho d / s^2), with I0 scaled for stability.
    def integrand(rho):
        return rho / sigma ** 2 * np.exp(-(rho - d) ** 2 / (2 * sigma ** 2)) * i0e(rho * d / sigma ** 2)
    return quad(integrand, 0.0, radius)[0]


def test_clean_look_renders_bit_for_bit_as_the_scenario_did():
    scenario = paper_scenario('1080p', points=2, postures=1)
    clean = apply_look(scenario, LOOKS['clean'])
    for index in range(len(scenario.poses)):
        before = render_frame(scenario.camera, scenario.poses[index], scenario.lamps, scenario.sensor,
                              float(scenario.frame_times()[index]), np.random.default_rng(index))
        assert np.array_equal(clean.render(index, np.random.default_rng(index)).image, before.image)
    assert clean.locator_parameters(True) == scenario.locator_parameters(True)


def test_glare_halo_is_the_disc_spread_by_its_gaussian_peaking_at_its_fraction_of_the_level():
    radius_px, width = 30.0, 0.35
    plain, glared = render(lamp(), sensor()), render(lamp(), sensor(glare=0.2, glare_width=width))
    halo = glared - plain
    centre = (240, 320)  # (row, column) of a lamp straight above the principal point, (319.5, 239.5)
    assert halo[centre] == pytest.approx(0.2 * LEVEL, abs=1.5)
    sigma = width * 2 * radius_px
    peak = blurred_disc(0.0, radius_px, sigma)
    for d in (1.3 * radius_px, 2.0 * radius_px, 3.0 * radius_px):
        expected = 0.2 * LEVEL * blurred_disc(d, radius_px, sigma) / peak
        measured = halo[centre[0], int(round(319.5 + d))]
        assert measured == pytest.approx(expected, abs=1.0 + 0.03 * expected)
    # A halo, not a disc: still lit 2.5 radii from the centre; nothing at the frame's edge, 10 radii out.
    assert halo[240, 320 + int(2.5 * radius_px)] > 0.01 * LEVEL * 0.2
    assert np.all(glared[:, :20] == 0.0)


def test_glare_halo_is_lit_row_by_row_as_the_lamp_and_carries_the_stripes():
    modulated = packet_waveform(3, 4000.0, 0.6, offset=1.1e-4)
    model = sensor(glare=0.2)
    steady_halo = render(lamp(), model) - render(lamp(), sensor())
    striped = render(lamp(waveform=modulated), model)
    rows = np.arange(200, 281)
    level = modulated.mean_brightness(rows * model.row_time, model.exposure)
    assert np.ptp(level) > 0.5
    # Beside the disc (1.4 radii out) the light is the halo alone, scaled by the row's level.
    column = 320 + 42
    np.testing.assert_allclose(striped[rows, column], steady_halo[rows, column] * level, atol=1.0)
    assert np.ptp(striped[rows, column]) > 8.0


def test_diffuser_falloff_dims_the_rim_by_its_fraction():
    image = render(lamp(radius=0.1, falloff=0.3), sensor())
    centre, rim = image[240, 320], image[240, round(319.5 + 0.9 * 60)]
    assert centre == pytest.approx(LEVEL, abs=1.0)
    assert rim / centre == pytest.approx(1.0 - 0.3 * 0.9 ** 2, abs=0.01)
    flat = render(lamp(radius=0.1), sensor())
    assert flat[240, round(319.5 + 0.9 * 60)] == pytest.approx(LEVEL, abs=1.0)


def test_blooming_spills_charge_beyond_a_saturated_disc_and_nowhere_else():
    bright = lamp(radius=0.05)
    bright = SimLamp(bright.lamp, STEADY, peak_dn=3 * LEVEL, color_bgr=WHITE, marker_radius=bright.marker_radius)
    clipped, spilled = render(bright, sensor()), render(bright, sensor(bloom=0.3, bloom_sigma=2.0))
    assert clipped[240, 320] == 255.0 and spilled[240, 320] == 255.0
    # Beyond the rim (at column 349.5) the spill is bloom x the excess charge spread by its Gaussian;
    # 20 px out, nothing.
    columns = np.arange(351, 355)
    expected = 0.3 * (3 * LEVEL - 255.0) * norm.cdf(-(columns - 349.5) / 2.0)
    np.testing.assert_allclose(spilled[240, columns] - clipped[240, columns], expected, atol=1.5)
    assert spilled[240, 320 + 50] == clipped[240, 320 + 50] == 0.0
    assert np.array_equal(render(lamp(), sensor(bloom=0.3)), render(lamp(), sensor()))


@pytest.mark.parametrize('distance', [0.5, 0.9, 1.0])
def test_marker_renders_where_the_map_puts_it_from_inside_to_straddling_the_rim(distance):
    sim = lamp(radius=0.1, marker_distance=distance, marker_radius=0.1)
    frame = render_frame(camera(), UP, [sim], sensor(), 0.0, None)
    red = np.clip(frame.image[..., 2].astype(float) - frame.image[..., 1], 0.0, None)
    ys, xs = np.nonzero(red > 0.0)
    centroid = np.array([np.sum(xs * red[ys, xs]), np.sum(ys * red[ys, xs])]) / red[ys, xs].sum()
    truth = frame.truth(sim.lamp.id)
    np.testing.assert_allclose(centroid, truth.marker_pixel, atol=0.2)
    # Its area is that of a disc of 0.1 r (6 px), wherever it sits: a straddling marker glows beyond the rim.
    assert red.sum() / red.max() == pytest.approx(np.pi * 6.0 ** 2, rel=0.05)
    beyond = np.hypot(xs - truth.center_pixel[0], ys - truth.center_pixel[1]) > 60.5
    assert np.any(beyond) == (distance == 1.0)


def test_clutter_lamps_are_steady_markerless_and_not_in_the_map():
    scenario = apply_look(paper_scenario('1080p', points=1, postures=1), Look(clutter=2))
    assert len(scenario.clutter) == 2
    names = scenario.locator_parameters(True)['leds']['names']
    assert names == ['lamp']
    for clutter in scenario.clutter:
        distance = np.linalg.norm(clutter.lamp.position - scenario.lamps[0].lamp.position)
        assert distance == pytest.approx(10 * scenario.lamps[0].lamp.radius)
        assert clutter.lamp.radius == scenario.lamps[0].lamp.radius
    # Render one straight above the camera: its rows all read the same, and nothing on it is red.
    sim = scenario.clutter[0]
    shown = render_frame(camera(), Pose(np.eye(3), sim.lamp.position - [0.0, 0.0, 1.0]), [sim], sensor(), 0.0, None)
    disc = shown.image[240 - 20:240 + 20, 320 - 20:320 + 20].astype(float)
    assert np.ptp(disc[..., 1]) <= 1.0 and np.all(disc[..., 2] - disc[..., 1] < 10.0)
    frame = scenario.render(0, None)
    assert {t.lamp_id for t in scenario.mapped_truths(frame)} == {11}


def test_jpeg_goes_into_the_bag_as_compressed_image_and_decodes_to_the_frame(tmp_path):
    scenario = apply_look(paper_scenario('1080p', points=1, postures=2), Look(jpeg_quality=90))
    record(scenario, tmp_path / 'bag', 'mcap', False, np.random.default_rng(5))
    write_params(tmp_path / 'params.yaml', scenario, False)
    with Reader(tmp_path / 'bag') as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics[COMPRESSED_TOPIC] == 'sensor_msgs/msg/CompressedImage' and '/image_raw' not in topics
        raw = [data for c, _, data in reader.messages() if c.topic == COMPRESSED_TOPIC]
    assert len(raw) == 2
    assert TYPESTORE.deserialize_cdr(raw[0], 'sensor_msgs/msg/CompressedImage').format == JPEG_FORMAT
    # The locator's own decoder reads it back to the rendered frame, within JPEG q90's error.
    decoded = decode_compressed(parse_compressed_image(bytes(raw[0])))
    rendered = scenario.render(0, np.random.default_rng(5)).image
    assert decoded.shape == rendered.shape
    error = decoded.astype(float) - rendered
    assert np.sqrt(np.mean(error ** 2)) < 2.0 and 0.0 < np.abs(error).max() < 60.0
    np.testing.assert_array_equal(transported(scenario, rendered),
                                  decode_compressed(parse_compressed_image(bytes(raw[0]))))
    params = yaml.safe_load((tmp_path / 'params.yaml').read_text())['vlp_locator']['ros__parameters']
    assert params['image_transport'] == 'compressed'


def stripe_period_rows(image: np.ndarray, rows: slice, column: int) -> float:
    """Return the dominant period (rows) of the stripes down ``column``, from a zero-padded spectrum."""
    profile = image[rows, column] - image[rows, column].mean()
    spectrum = np.abs(np.fft.rfft(profile * np.hanning(profile.size), 64 * profile.size))
    frequencies = np.fft.rfftfreq(64 * profile.size)
    return 1.0 / frequencies[np.argmax(spectrum[1:]) + 1]


def test_row_time_error_changes_the_true_stripes_but_the_params_keep_the_nominal_row_time():
    scenario = robot_tone_scenario(frames=1)
    erred = apply_look(scenario, Look(row_time_error=0.02))
    nominal = scenario.sensor.row_time
    assert erred.locator_parameters(False)['beacon']['row_time'] == pytest.approx(nominal, rel=1e-12)
    assert erred.sensor.row_time == pytest.approx(1.02 * nominal, rel=1e-12)
    # A big tone lamp straight above: its stripes repeat every 1 / (f x true row time) rows.
    tone = tone_waveform(4000.0, 0.8)
    big = SimLamp(Lamp('t', 1, [0.0, 0.0, 1.0], 0.15), tone, peak_dn=LEVEL, color_bgr=WHITE)
    for model in (scenario.sensor, erred.sensor):
        quiet = SensorModel(row_time=model.row_time, exposure=model.exposure, ambient_bgr=(0.0, 0.0, 0.0),
                            blur_sigma=0.0)
        image = render(big, quiet)
        period = stripe_period_rows(image, slice(240 - 80, 240 + 80), 300)
        assert period == pytest.approx(1.0 / (4000.0 * model.row_time), rel=0.005)


def test_realistic_look_is_the_independent_renderers():
    realistic = LOOKS['realistic']
    assert (realistic.blur_sigma, realistic.glare, realistic.glare_width, realistic.falloff) == (1.6, 0.2, 0.35, 0.3)
    assert realistic.clutter == 2 and realistic.brightness > 1.0 and realistic.depth == 0.6
    assert LOOKS['realistic_jpeg'].jpeg_quality == 90
    scenario = apply_look(with_rim_markers(paper_scenario('4k', points=1, postures=1)), realistic)
    assert (scenario.sensor.blur_sigma, scenario.sensor.image_blur) == (0.0, 1.6)
    assert all(s.falloff == 0.3 and s.waveform.depth == 0.6 for s in scenario.lamps) and scenario.beacon.depth == 0.6
    with pytest.raises(ValueError, match='Bayer'):
        apply_look(paper_scenario('1080p', points=1, postures=1, bayer='rggb'), LOOKS['jpeg'])


@pytest.mark.parametrize('option, value, message', [
    ('--falloff', '1.5', 'falloff must be in [0, 1)'),
    ('--jpeg', '0', 'JPEG quality must be in [1, 100]'),
    ('--row-time-error', '0.5', 'row-time error must be within'),
    ('--marker-distance', '1.2', 'marker distance must be in [0, 1]'),
])
def test_command_line_rejects_bad_looks_in_one_line(tmp_path, capsys, option, value, message):
    assert cli.main(['--scenario', 'paper', option, value, '--out', str(tmp_path / 'out')]) == 2
    error = capsys.readouterr().err
    assert message in error and len(error.strip().splitlines()) == 1


def test_command_line_records_a_look_with_its_options(tmp_path, capsys):
    out = tmp_path / 'out'
    status = cli.main(['--scenario', 'paper', '--camera', '1080p', '--points', '1', '--postures', '2',
                       '--out', str(out), '--look', 'realistic_jpeg', '--row-time-error', '0.015',
                       '--marker-distance', '0.9', '--still-interval', '0.1'])
    assert status == 0 and 'look realistic_jpeg' in capsys.readouterr().out
    with Reader(out / 'paper_1080p') as reader:
        stamps = [t for c, t, _ in reader.messages() if c.topic == COMPRESSED_TOPIC]
    assert np.diff(stamps) == pytest.approx([1e8], abs=1)
    params = yaml.safe_load((out / 'params.yaml').read_text())['vlp_locator']['ros__parameters']
    assert params['image_transport'] == 'compressed' and 'continuity' not in params
    assert params['leds']['lamp']['marker_distance'] == pytest.approx(0.9 * params['leds']['lamp']['radius'])
    nominal = paper_scenario('1080p', points=1, postures=1).sensor.row_time
    assert params['beacon']['row_time'] == pytest.approx(nominal, rel=1e-9)


@pytest.mark.simulation
def test_look_check_finds_our_own_realistic_frames_match_our_realistic_look(tmp_path, capsys):
    scenario = apply_look(with_rim_markers(paper_scenario('1080p', points=1, postures=2, seed=4)),
                          LOOKS['realistic_jpeg'])
    record(scenario, tmp_path / 'bag', 'mcap', False, np.random.default_rng(2))
    write_params(tmp_path / 'params.yaml', scenario, False)
    assert look_check.main([str(tmp_path), '--look', 'realistic']) == 0
    halo_table, outcome_table = capsys.readouterr().out.split('Pipeline outcome')
    lines = [line.split() for line in halo_table.splitlines() if line.split()[3:4] in (['theirs'], ['ours'])]
    assert len(lines) == 4
    # Each frame of both went through a pipeline: one line per frame.
    outcomes = [line.split() for line in outcome_table.splitlines()[3:]]
    assert len(outcomes) == 2
    for theirs, ours in zip(lines[::2], lines[1::2]):
        assert theirs[3] == 'theirs' and ours[3] == 'ours'
        halo_theirs, halo_ours = np.array(theirs[4:10], dtype=float), np.array(ours[4:10], dtype=float)
        assert halo_theirs[0] > 10.0
        np.testing.assert_allclose(halo_ours, halo_theirs, atol=3.0)
        assert abs(float(theirs[10]) - float(ours[10])) < 15.0


def test_optics_blur_keeps_the_stripes_sharp_and_image_blur_smooths_them():
    modulated = packet_waveform(3, 4000.0, 0.6, offset=1.1e-4)
    big = lamp(radius=0.1, waveform=modulated)
    rows = np.arange(200, 281)
    model = sensor()
    level = LEVEL * modulated.mean_brightness(rows * model.row_time, model.exposure)
    # The lens blurs the scene before the rolling shutter: inside the disc each row keeps its own level.
    optics = render(big, sensor(blur_sigma=2.0))
    np.testing.assert_allclose(optics[rows, 320], level, atol=0.6)
    # The recorded frame's blur mixes rows: the stripes come out convolved with the same Gaussian.
    smoothed = render(big, sensor(image_blur=2.0))
    all_rows = np.arange(480)
    profile = LEVEL * modulated.mean_brightness(all_rows * model.row_time, model.exposure)
    kernel = norm.pdf(np.arange(-8, 9), scale=2.0)
    expected = np.convolve(profile, kernel / kernel.sum(), mode='same')[rows]
    np.testing.assert_allclose(smoothed[rows, 320], expected, atol=1.0)
    assert np.max(np.abs(smoothed[rows, 320] - level)) > 20.0  # the edges of the stripes are soft

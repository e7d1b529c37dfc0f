"""Loop closure: stereo place features against the renderer's depth, a loop between two
rendered keyframes against the simulated relative pose, a different scene refused, the
temporal-consistency cache, and loop edges that pull a drifted trajectory back."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from msf_torch.sensors.camera import CameraRig
from msf_torch.sim.render import RunRenderer, render_radiance
from msf_torch.vision.geometry import rotation_log
from msf_torch.vision.loop import (
    ConsistencyConfig,
    LoopClosure,
    LoopConfig,
    LoopDetector,
    PlaceFeatures,
    TemporalConsistencyCache,
    close_loops,
    consistent_loops,
    describe_place,
    loop_pose_graph,
    odometry_edge_covariance,
    odometry_scale,
    refine_pose,
)
from msf_torch.vision.vocabulary import build_vocabulary


@pytest.fixture(scope="module")
def places(rendered):
    _, renderer, frames = rendered
    return [describe_place(f.left, f.right, renderer.rig) for f in frames[::5]]


@pytest.fixture(scope="module")
def vocabulary(places):
    descriptors = np.concatenate([p.descriptors for p in places])
    image = np.concatenate([np.full(len(p.descriptors), k) for k, p in enumerate(places)])
    return build_vocabulary(descriptors, image, branching=8, depth=3)


def test_place_depths_match_rendered_depth(rendered, places):
    _, renderer, frames = rendered
    rig = renderer.rig
    place = places[0]
    centre, rotation_wc = renderer.camera_pose(frames[0].position, frames[0].rotation)
    _, distance = render_radiance(renderer.scene, rig, centre, rotation_wc)
    has_depth = np.isfinite(place.points[:, 0])
    assert len(place.pixels) >= 500 and has_depth.sum() >= 150
    pixel = np.rint(place.pixels[has_depth]).astype(int)
    ray = np.stack(((pixel[:, 0] - rig.cx) / rig.fx, (pixel[:, 1] - rig.cy) / rig.fy), -1)
    # the rendered range around each keypoint; corners on a depth edge (box silhouettes,
    # the horizon) have no single true depth and are left out
    offsets = np.arange(-2, 3)
    rows = np.clip(pixel[:, 1, None, None] + offsets[None, :, None], 0, rig.height - 1)
    cols = np.clip(pixel[:, 0, None, None] + offsets[None, None, :], 0, rig.width - 1)
    around = distance[rows, cols].reshape(len(pixel), -1)
    finite = np.isfinite(around).all(1)
    around = np.where(finite[:, None], around, 1.0)  # sky: no range
    smooth = finite & (np.ptp(around, axis=1) < 0.05 * around.min(1))
    true_depth = distance[pixel[:, 1], pixel[:, 0]] / np.sqrt(1.0 + (ray**2).sum(-1))
    fb = rig.fx * rig.baseline_m
    error_px = np.abs(fb / place.points[has_depth, 2] - fb / true_depth)[smooth]
    # measured (seed 3, frame 0): 314 of 663 off edges, median 0.085 px, 97 % below 0.5 px
    assert smooth.sum() >= 150
    assert np.median(error_px) < 0.15 and np.mean(error_px < 0.5) > 0.9


def _truth_relative(frames, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
    a, b = frames[i], frames[j]
    return a.rotation.T @ b.rotation, a.rotation.T @ (b.position - a.position)


def test_loop_between_rendered_keyframes_matches_truth(rendered, places, vocabulary):
    _, renderer, frames = rendered
    config = LoopConfig(min_gap_s=1.0, prior_dt_s=1.0, min_consistent=0)
    detector = LoopDetector(vocabulary, renderer.rig, config)
    detector.process(frames[0].t, places[0])
    loop, record = detector.process(frames[15].t, places[3])
    assert record["candidate"] == 0 and loop is not None
    rotation, translation = _truth_relative(frames, 0, 15)
    assert np.linalg.norm(translation) > 1.5
    assert np.linalg.norm(loop.translation - translation) < 0.03
    assert np.degrees(np.linalg.norm(rotation_log(rotation.T @ loop.rotation))) < 0.2
    error = np.concatenate(
        (loop.translation - translation, rotation_log(rotation.T @ loop.rotation))
    )
    # the declared covariance is not overconfident: chi-square(6) 99.9 % = 22.5
    assert error @ np.linalg.solve(loop.covariance, error) < 22.5


def test_different_scene_is_refused(rendered, places, vocabulary):
    run, renderer, frames = rendered
    other = RunRenderer.for_run(run, renderer.scene.config, scene_seed=99, seed=3)
    frame = other.frame(15)
    foreign = describe_place(frame.left, frame.right, renderer.rig)
    config = LoopConfig(min_gap_s=1.0, min_consistent=0, min_normalized_score=0.0)
    detector = LoopDetector(vocabulary, renderer.rig, config)
    detector.process(frames[0].t, places[0])
    loop, record = detector.process(frames[15].t, foreign)
    assert record["candidate"] == 0 and record["consistent"]
    assert loop is None and not record["verified"]


def _synthetic_place(rng, rig, body_pose, world, descriptors) -> PlaceFeatures:
    """What a camera on ``rig`` at body pose (4, 4) sees of world points (P, 3) with their
    descriptors: pixels with 0.3 px noise, exact camera-frame points, 5 % of the bytes with
    one bit flipped."""
    mount = np.eye(4)
    mount[:3, :3], mount[:3, 3] = rig.body_rotation_cam(), rig.body_translation_cam()
    camera = body_pose @ mount
    points = (world - camera[:3, 3]) @ camera[:3, :3]
    pixels = rig.project(points)
    seen = (points[:, 2] > 0.5) & (pixels >= 0).all(1)
    seen &= (pixels[:, 0] < rig.width) & (pixels[:, 1] < rig.height)
    flips = (rng.random((seen.sum(), 32)) < 0.05) << rng.integers(0, 8, (seen.sum(), 32))
    return PlaceFeatures(
        pixels[seen] + rng.normal(0.0, 0.3, (seen.sum(), 2)),
        descriptors[seen] ^ flips.astype(np.uint8),
        points[seen],
        np.ones(seen.sum()),
    )


def test_loop_on_a_synthetic_scene_with_an_offset_pitched_mount():
    """Two views of known 3-D points from a camera mounted off-axis (0.1 m left, 1 m up,
    pitched 25 deg, cx != cy): the loop is ``T_match^-1 T_query`` of the bodies; the same
    descriptors on another scene's points, or the query's depths scaled by 1.3, are
    refused."""
    rng = np.random.default_rng(0)
    rig = CameraRig(
        fx=420.0, fy=410.0, cx=310.0, cy=250.0, mount_position_m=(0.4, 0.1, 1.0),
        mount_pitch_deg=25.0,
    )  # fmt: skip
    world = rng.uniform([3.0, -6.0, -1.0], [15.0, 6.0, 2.0], (600, 3))
    descriptors = rng.integers(0, 256, (600, 32), dtype=np.uint8)
    poses = []
    for yaw, position in ((0.0, [0.0, 0.0, 0.0]), (0.12, [0.6, 0.3, 0.05])):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_euler("zyx", [yaw, 0.02, -0.01]).as_matrix()
        pose[:3, 3] = position
        poses.append(pose)
    truth = np.linalg.inv(poses[0]) @ poses[1]
    vocabulary = build_vocabulary(descriptors, np.arange(600) // 60, branching=4, depth=2)
    config = LoopConfig(min_gap_s=1.0, min_consistent=0, min_normalized_score=0.0)
    match = _synthetic_place(rng, rig, poses[0], world, descriptors)
    other_world = rng.uniform([3.0, -6.0, -1.0], [15.0, 6.0, 2.0], (600, 3))
    query = _synthetic_place(rng, rig, poses[1], world, descriptors)
    scaled = PlaceFeatures(query.pixels, query.descriptors, 1.3 * query.points, query.scales)
    loops = []
    for place in (query, _synthetic_place(rng, rig, poses[1], other_world, descriptors), scaled):
        detector = LoopDetector(vocabulary, rig, config)
        detector.process(0.0, match)
        loop, record = detector.process(30.0, place)
        assert record["candidate"] == 0
        loops.append(loop)
    loop = loops[0]
    assert loop is not None and loops[1] is None and loops[2] is None
    # measured: 1.1 mm and 0.006 deg
    assert np.abs(loop.translation - truth[:3, 3]).max() < 0.005
    assert np.degrees(np.linalg.norm(rotation_log(loop.rotation.T @ truth[:3, :3]))) < 0.05


def test_temporal_consistency_cache():
    cache = TemporalConsistencyCache(window_s=3.0, distance_s=2.0)
    assert cache.observe(10.0, 50.0, 52.0) == 0  # first sighting
    assert cache.observe(11.0, 53.5, 54.0) == 1  # 1.5 s after the first island ends
    assert cache.observe(12.0, 80.0, 81.0) == 0  # another place
    assert cache.observe(13.5, 55.0, 55.5) == 1  # the 10.0 entry has expired (3.5 s)
    cache.forget(20.0)
    assert cache.entries == []
    assert cache.observe(20.0, 55.0, 56.0) == 0


def _drifted_square(count: int = 40):
    """Truth: two laps of a square path (the second offset by 0.3 m); the odometry has a
    yaw drift and a scale error; loops join each second-lap pose to its first-lap twin."""
    side = count // 8
    corners = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]], float)
    lap = np.concatenate(
        [np.linspace(corners[k], corners[k + 1], side, endpoint=False) for k in range(4)]
    )
    xy = np.concatenate((lap, lap + [0.3, 0.0]))
    heading = np.arctan2(*np.diff(np.concatenate((xy, xy[:1])), axis=0).T[::-1])
    position = np.concatenate((xy, np.zeros((count, 1))), 1)
    rotation = np.stack(
        [[[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]] for a in heading]
    )
    est_p, est_r = [position[0]], [rotation[0]]
    drift = np.array([[np.cos(0.01), -np.sin(0.01), 0], [np.sin(0.01), np.cos(0.01), 0], [0, 0, 1]])
    for k in range(count - 1):
        rel_r = rotation[k].T @ rotation[k + 1]
        rel_t = 1.02 * rotation[k].T @ (position[k + 1] - position[k])
        est_p.append(est_p[-1] + est_r[-1] @ rel_t)
        est_r.append(est_r[-1] @ rel_r @ drift)
    loops = []
    for j in range(count // 2, count):
        i = j - count // 2
        loops.append(
            LoopClosure(
                query=j,
                match=i,
                query_time=float(j),
                match_time=float(i),
                rotation=rotation[i].T @ rotation[j],
                translation=rotation[i].T @ (position[j] - position[i]),
                covariance=np.diag([1e-4] * 3 + [1e-6] * 3),
                inliers=100,
                matches=120,
                score=1.0,
            )
        )
    return position, rotation, np.array(est_p), np.array(est_r), loops


def test_loop_edges_pull_a_drifted_trajectory_back():
    position, _, est_p, est_r, loops = _drifted_square()
    covariance = odometry_edge_covariance(est_p, est_r)
    graph = loop_pose_graph(est_p, est_r, loops, covariance)
    assert graph.num_edges == len(est_p) - 1 + len(loops)
    np.testing.assert_array_equal(graph.edge_index[-1].numpy(), [loops[-1].match, loops[-1].query])
    corrected_p, _, result = close_loops(est_p, est_r, loops, covariance)
    assert result.converged
    before = np.linalg.norm(est_p - position, axis=1)
    after = np.linalg.norm(corrected_p - position, axis=1)
    assert before.max() > 2.0 and after.max() < 0.35 * before.max()


def test_refine_pose_recovers_pose_with_calibrated_covariance():
    """Monte Carlo: points near and far, pixel noise and depth noise along the rays drawn
    from the model; the refined pose's error has chi-square(6) statistics."""
    rng = np.random.default_rng(5)
    camera_matrix = np.array([[400.0, 0, 319.5], [0, 400.0, 239.5], [0, 0, 1]])
    count = 80
    true_rvec, true_tvec = np.array([0.02, -0.05, 0.01]), np.array([0.4, -0.1, 0.8])
    rotation = Rotation.from_rotvec(true_rvec).as_matrix()
    pixel_sigma = np.full(count, 0.7)
    nis = []
    for _ in range(200):
        depth = rng.uniform(3.0, 25.0, count)
        bearing = np.stack((rng.uniform(-0.6, 0.6, count), rng.uniform(-0.3, 0.4, count)), -1)
        points = np.concatenate((bearing * depth[:, None], depth[:, None]), 1)
        depth_sigma = depth**2 * 0.3 / 48.0
        camera = points @ rotation.T + true_tvec
        pixels = camera[:, :2] / camera[:, 2:] * 400.0 + [319.5, 239.5]
        noisy_points = points * (1.0 + rng.standard_normal(count) * depth_sigma / depth)[:, None]
        noisy_pixels = pixels + rng.standard_normal((count, 2)) * pixel_sigma[:, None]
        rvec, tvec, covariance, chi2 = refine_pose(
            noisy_points,
            noisy_pixels,
            pixel_sigma,
            depth_sigma,
            np.zeros(3),
            np.zeros(3),
            camera_matrix,
        )
        error = np.concatenate((rvec - true_rvec, tvec - true_tvec))
        nis.append(error @ np.linalg.solve(covariance, error))
    assert chi2.shape == (count,)
    # mean of chi-square(6) over 200 draws: 6 +- 0.25 (one sigma)
    assert 5.0 < np.mean(nis) < 7.0


def _loops_on_a_line(count: int, corrupt: list[int], isolated: bool):
    """Keyframes along x (1 m apart, twice: the second pass 100 s later, 0.2 m to the side);
    loops from each second-pass keyframe to its twin, exact except ``corrupt`` (0.6 m)."""
    positions = np.concatenate(
        (
            np.stack((np.arange(count), np.zeros(count), np.zeros(count)), -1),
            np.stack((np.arange(count), np.full(count, 0.2), np.zeros(count)), -1),
        )
    )
    rotations = np.repeat(np.eye(3)[None], 2 * count, 0)
    loops = []
    queries = list(range(count)) if not isolated else [0, count // 2]
    for k in queries:
        translation = np.array([0.0, 0.2, 0.0]) + (np.array([0.6, 0.0, 0.0]) if k in corrupt else 0)
        loops.append(
            LoopClosure(
                query=count + k,
                match=k,
                query_time=100.0 + k,
                match_time=float(k),
                rotation=np.eye(3),
                translation=translation,
                covariance=np.diag([0.03**2] * 3 + [0.003**2] * 3),
                inliers=80,
                matches=100,
                score=1.0,
            )
        )
    return positions, rotations, loops


def test_pairwise_consistency_drops_wrong_and_isolated_loops():
    positions, rotations, loops = _loops_on_a_line(20, corrupt=[6, 7, 13], isolated=False)
    keep = consistent_loops(loops, positions, rotations, ConsistencyConfig(window_s=5.0))
    expected = np.ones(20, bool)
    expected[[6, 7, 13]] = False
    np.testing.assert_array_equal(keep, expected)
    # two loops 10 s apart have no partner within 5 s: neither is confirmed
    positions, rotations, loops = _loops_on_a_line(20, corrupt=[], isolated=True)
    keep = consistent_loops(loops, positions, rotations, ConsistencyConfig(window_s=5.0))
    assert not keep.any()


def test_detector_accepts_a_revisit_only_when_seen_again(rendered, places, vocabulary):
    """Keyframes of frames 0, 10, 20 stored at 0-2 s; revisits by frames 5 and 15 at 30 and
    31 s. The first revisit is a candidate but not yet consistent; the second, whose
    candidate island agrees with the first's, is verified against the simulated pose."""
    _, renderer, frames = rendered
    detector = LoopDetector(vocabulary, renderer.rig, LoopConfig())
    for t, k in ((0.0, 0), (1.0, 2), (2.0, 4)):
        loop, record = detector.process(t, places[k])
        assert loop is None and record["candidate"] == -1
    loop, record = detector.process(30.0, places[1])
    assert loop is None and record["candidate"] >= 0 and not record["consistent"]
    loop, record = detector.process(31.0, places[3])
    assert record["consistent"] and loop is not None
    assert (loop.query, loop.match) == (4, record["candidate"])
    assert loop.match in (1, 2)  # frames 10 and 20, either side of frame 15
    rotation, translation = _truth_relative(frames, 5 * 2 * loop.match, 15)
    assert np.linalg.norm(loop.translation - translation) < 0.05
    assert np.degrees(np.linalg.norm(rotation_log(rotation.T @ loop.rotation))) < 0.3
    # the normaliser is the score against the keyframe at t - 1 s (frame 5, stored at 30 s)
    scores = detector.database.scores(detector.database.vectors[4])
    assert loop.score == pytest.approx(scores[loop.match] / scores[3])
    # asking for two earlier agreeing queries: the same revisit is not yet accepted
    strict = LoopDetector(vocabulary, renderer.rig, LoopConfig(min_consistent=2))
    for t, k in ((0.0, 0), (1.0, 2), (2.0, 4), (30.0, 1)):
        strict.process(t, places[k])
    loop, record = strict.process(31.0, places[3])
    assert loop is None and not record["consistent"]


def test_odometry_scale_is_the_least_squares_step_ratio():
    rng = np.random.default_rng(2)
    metric = np.cumsum(rng.normal(0.0, 0.5, (60, 3)), axis=0)
    rotation = Rotation.from_rotvec([0.1, -0.2, 1.0]).as_matrix()
    # the same path 0.4 % short, in another frame: exactly 1 / 0.996
    odometry = 0.996 * metric @ rotation.T + [3.0, -1.0, 0.5]
    assert odometry_scale(odometry, metric) == pytest.approx(1.0 / 0.996, rel=1e-12)
    # noisy steps: against numpy's least squares on the step lengths
    noisy = metric + rng.normal(0.0, 0.02, metric.shape)
    steps = np.linalg.norm(np.diff(noisy, axis=0), axis=1)[:, None]
    target = np.linalg.norm(np.diff(metric, axis=0), axis=1)
    expected = np.linalg.lstsq(steps, target, rcond=None)[0][0]
    assert odometry_scale(noisy, metric) == pytest.approx(expected, rel=1e-12)
    assert odometry_scale(np.zeros((5, 3)), metric[:5]) == 1.0


def _drifted(frames, k: int, drift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frame k's body pose in an odometry frame that drifted by the transform ``drift``."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = frames[k].rotation, frames[k].position
    moved = drift @ pose
    return moved[:3, 3], moved[:3, :3]


def test_recent_loop_predicts_the_next_match(rendered, places, vocabulary):
    """First lap: frames 0, 10, 20, 30 at 0-3 s with their true poses; second lap: frames 5,
    15, 25 at 30-32 s in an odometry frame that drifted by 1.2 m and 8 deg of yaw. The loop
    at 31 s comes from the bag of words; at 32 s that loop and the odometry predict the
    match, which is verified first (from the predicted pose) and agrees with the simulated
    relative pose. Without poses the same query goes through the bag of words."""
    _, renderer, frames = rendered
    drift = np.eye(4)
    drift[:3, :3] = Rotation.from_euler("z", 8.0, degrees=True).as_matrix()
    drift[:3, 3] = [1.2, -0.7, 0.05]
    lap = ((0.0, 0), (1.0, 2), (2.0, 4), (3.0, 6))
    revisit = ((30.0, 1), (31.0, 3), (32.0, 5))
    with_poses = LoopDetector(vocabulary, renderer.rig, LoopConfig())
    without = LoopDetector(vocabulary, renderer.rig, LoopConfig())
    for t, k in lap:
        with_poses.process(t, places[k], frames[5 * k].position, frames[5 * k].rotation)
        without.process(t, places[k])
    records = []
    for t, k in revisit:
        loop, record = with_poses.process(t, places[k], *_drifted(frames, 5 * k, drift))
        records.append((loop, record))
        without.process(t, places[k])
    (_, first), (loop_bow, second), (loop, third) = records
    assert not first["propagated"] and loop_bow is not None and not second["propagated"]
    assert loop is not None and third["propagated"] and third["verified"]
    assert loop.query == 6 and loop.match in (2, 3)  # frames 20 / 30, beside frame 25
    rotation, translation = _truth_relative(frames, 10 * loop.match, 25)
    assert np.linalg.norm(loop.translation - translation) < 0.05
    assert np.degrees(np.linalg.norm(rotation_log(rotation.T @ loop.rotation))) < 0.3
    assert with_poses.loops[-1] is loop
    _, plain = without.process(33.0, places[5])
    assert not plain["propagated"]


def test_prediction_needs_a_recent_loop_and_a_nearby_keyframe(rendered, places, vocabulary):
    """No prediction once the last loop is older than propagation_window_s, nor when the
    odometry puts the query farther than propagation_radius_m from every stored keyframe."""
    _, renderer, frames = rendered
    for config, query_t, shift in (
        (LoopConfig(propagation_window_s=0.5), 32.0, 0.0),
        (LoopConfig(propagation_radius_m=0.4), 32.0, 3.0),
    ):
        detector = LoopDetector(vocabulary, renderer.rig, config)
        for t, k in ((0.0, 0), (1.0, 2), (2.0, 4), (3.0, 6)):
            detector.process(t, places[k], frames[5 * k].position, frames[5 * k].rotation)
        for t, k in ((30.0, 1), (31.0, 3)):
            detector.process(t, places[k], frames[5 * k].position, frames[5 * k].rotation)
        assert detector.loops, "the bag-of-words loop at 31 s seeds the prediction"
        position = frames[25].position + frames[25].rotation @ [0.0, shift, 0.0]
        _, record = detector.process(query_t, places[5], position, frames[25].rotation)
        assert not record["propagated"]


def test_loose_loop_is_refused(rendered, places, vocabulary):
    """A loop whose translation sigma exceeds max_translation_sigma_m is refused (the
    translation floor alone is 0.02 m)."""
    _, renderer, frames = rendered
    for limit, accepted in ((0.1, True), (0.015, False)):
        config = LoopConfig(min_gap_s=1.0, min_consistent=0, max_translation_sigma_m=limit)
        detector = LoopDetector(vocabulary, renderer.rig, config)
        detector.process(frames[0].t, places[0])
        loop, _ = detector.process(frames[15].t, places[3])
        assert (loop is not None) == accepted


def test_benchmark_edge_sigmas_fit_the_rendered_odometry(rendered, odometry):
    """The benchmark's keyframe-odometry sigmas (fitted on its tuning seeds) against this
    rendered run's keyframe steps: whitened squared errors average near 1 per axis, while
    the generic drift model's average far below (too loose)."""
    from benchmarks.loop_closure import VO_EDGE_SIGMAS

    _, _, frames = rendered
    index = [kf.frame for kf in odometry.keyframes]
    vo_p = np.array([kf.position for kf in odometry.keyframes])
    vo_r = np.array([kf.rotation for kf in odometry.keyframes])
    true_p = np.array([frames[k].position for k in index])
    true_r = np.array([frames[k].rotation for k in index])
    errors = []
    for k in range(len(index) - 1):
        true_rel_r = true_r[k].T @ true_r[k + 1]
        true_rel_t = true_r[k].T @ (true_p[k + 1] - true_p[k])
        rel_r = vo_r[k].T @ vo_r[k + 1]
        rel_t = vo_r[k].T @ (vo_p[k + 1] - vo_p[k])
        errors.append(
            np.concatenate(
                (true_rel_r.T @ (rel_t - true_rel_t), rotation_log(true_rel_r.T @ rel_r))
            )
        )
    errors = np.array(errors)
    fitted = odometry_edge_covariance(vo_p, vo_r, **VO_EDGE_SIGMAS)
    generic = odometry_edge_covariance(vo_p, vo_r)
    per_axis_fitted = np.mean(errors**2 / np.diagonal(fitted, axis1=1, axis2=2))
    per_axis_generic = np.mean(errors**2 / np.diagonal(generic, axis1=1, axis2=2))
    assert 0.2 < per_axis_fitted < 2.0
    assert per_axis_generic < 0.3 * per_axis_fitted


def test_benchmark_frontend_cache_round_trip(tmp_path):
    """benchmarks/loop_closure.py's front-end cache returns the places and poses it wrote."""
    from benchmarks.loop_closure import load_frontend, save_frontend
    from msf_torch.vision.loop import PlaceFeatures

    rng = np.random.default_rng(0)
    places = [
        PlaceFeatures(
            rng.uniform(0, 640, (n, 2)),
            rng.integers(0, 256, (n, 32), dtype=np.uint8),
            np.where(rng.random((n, 1)) < 0.3, np.nan, rng.uniform(1, 9, (n, 3))),
            1.2 ** rng.integers(0, 4, n).astype(float),
        )
        for n in (5, 0, 9)
    ]
    front = {"kf_t": np.arange(3.0), "vo_p": rng.normal(size=(3, 3)), "places": places}
    save_frontend(tmp_path / "run.npz", front)
    back = load_frontend(tmp_path / "run.npz")
    np.testing.assert_array_equal(back["vo_p"], front["vo_p"])
    for a, b in zip(back["places"], places, strict=True):
        for name in ("pixels", "descriptors", "points", "scales"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))

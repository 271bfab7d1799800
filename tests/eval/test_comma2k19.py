"""The pose graph on the real comma2k19 drive (consumer GNSS + CAN speed + gyro)."""

from services.eval.comma2k19 import evaluate, load_segment


def test_segment_loads_into_a_consistent_local_frame(shared_data):
    s = load_segment(shared_data / "comma2k19" / "segment40")
    assert len(s["frame_t_ns"]) == len(s["frame_pose_true"]) > 1000
    assert abs(s["frame_pose_true"][0, 0]) < 1e-6  # origin at the first reference position


def test_pose_graph_beats_odometry_and_matches_gnss(shared_data):
    r = evaluate(shared_data / "comma2k19" / "segment40")
    assert r["length_m"] > 900
    assert r["pose_graph_smoothed_m"]["mean"] <= r["gnss_only_m"]["mean"] + 0.3
    assert r["pose_graph_smoothed_m"]["p90"] <= r["gnss_only_m"]["p90"] + 1.0
    assert r["pose_graph_committed_m"]["mean"] < r["odometry_only_m"]["mean"] / 3
    assert r["pose_graph_yaw_deg"]["mean"] < 2.0

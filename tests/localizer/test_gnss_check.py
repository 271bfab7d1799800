"""The GNSS as an integrity monitor: a map-matched pose on the wrong road is caught."""

import numpy as np

from common.config import LocalizerConfig
from services.localizer.gnss_check import GnssCheck
from services.localizer.localizer import get_localizer, replay
from services.localizer.map_cache import TileCache
from services.localizer.synthetic import fill_cache, frame_points, straight_road, synthetic_drive


def _fed(check, offset, rng, n):
    for _ in range(n):
        check.add(np.array(offset) + rng.normal(0, 0.4, 2), np.zeros(2), 2.5)
    return check


def test_a_receivers_bias_is_not_a_disagreement_but_a_parallel_road_is(rng):
    assert not _fed(GnssCheck(25, 3.0), (3.0, -3.5), rng, 100).disagrees  # a 4.6 m bias
    far = _fed(GnssCheck(25, 3.0), (0.0, 10.0), rng, 12)
    assert not far.heard and not far.disagrees  # under half a window: too early to tell
    far = _fed(far, (0.0, 10.0), rng, 1)
    assert far.heard and far.disagrees and abs(far.mean_residual_m - 10.0) < 0.5
    far.reset()
    assert not far.heard and far.mean_residual_m == 0.0
    assert not _fed(GnssCheck(25, 0.0), (0.0, 30.0), rng, 50).disagrees  # off


def test_a_filter_moved_onto_a_parallel_road_is_restarted_by_the_gnss(rng):
    """Mid-drive the filter is put 12 m to the side with a confident covariance (what a wrong
    initialization does). The consumer GNSS (4.6 m off itself, reporting 2.5 m) restarts it
    within 4 s, and no pose 5 m off is reported ok. Without the check only the single-fix
    gate restarts it, seconds later: one fix 9 m off passes a gate sized for its sigma."""
    cache = fill_cache(TileCache(capacity=30), straight_road())

    def run(alert_sigmas):
        streams = synthetic_drive(np.random.default_rng(3), duration_s=16.0,
                                  gnss_bias_m=(3.0, -3.5), gnss_reported_sigma_m=2.5)
        frames = [frame_points(cache, p, rng) for p in streams["frame_pose_true"]]
        loc = get_localizer(LocalizerConfig(gnss_alert_sigmas=alert_sigmas), cache)

        def displace(i, e):
            if i == 60:
                loc.ekf.reset(loc.ekf.pose + np.array([0.0, -12.0, 0.0]),
                              np.diag([0.05**2, 0.05**2, 1e-5]))
                loc.gnss_check.reset()  # as a fresh (wrong) start would
        est = replay(loc, streams, lambda i: frames[i], on_estimate=displace)
        err = [np.hypot(*(e.pose[:2] - t[:2])) for e, t in zip(est, streams["frame_pose_true"],
                                                                 strict=True)]
        return loc, est, np.array(err)

    loc, est, err = run(3.0)
    wrong = np.flatnonzero(err > 5.0)
    assert loc.inits == 2 and 60 <= wrong.min() and wrong.max() < 60 + 40
    assert not any(est[i].ok for i in wrong)
    assert err[-20:].max() < 0.5
    _, _, err = run(0.0)
    assert np.flatnonzero(err > 5.0).max() >= 60 + 50

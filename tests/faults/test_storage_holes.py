"""Issue 43 findings 5-8 at small counts: the scenarios of ground_station.lab.faults.storage_holes on the
real Controller and map worker behind the real FtpServer, the real OnboardLog in a real Storage, a real
`qnav log pull` process against a hostile MAVLink peer on UDP loopback, and real `qnav-robot` and
`qnav-sim` processes given a deeply nested --profile. `qnav bench faults` runs the same with large
counts."""

import pytest

from ground_station.lab.faults import storage_holes  # noqa: F401  (registers the scenarios)
from ground_station.lab.faults.common import SCENARIOS

NAMES = ["map_refused_stays_refused", "log_readonly_over_ftp", "log_pull_plain_names", "profile_deep_nesting"]


@pytest.mark.parametrize("name", NAMES)
def test_storage_hole(name):
    sc = SCENARIOS[name]
    res = sc.run(sc.small, seed=1)
    assert res.tried >= sc.small
    assert res.lost == 0, (res.failures, res.figures)

"""The parameter-list stream's pure core (firmware_py.mavlink.param_stream): a request
(re)starts its requester's stream, answers stay within the token bucket however many
requests arrive, several requesters share it round-robin, and a new one beyond
MAX_STREAMS replaces the longest-waiting."""

from firmware_py.mavlink.param_stream import ParamStream

N = 31


def test_a_whole_list_at_once_then_nothing_more():
    s = ParamStream(rate_hz=500, burst=32)
    s.request((255, 190))
    assert s.due(0, N) == [((255, 190), i) for i in range(N)]
    assert s.due(1_000_000, N) == [] and s.active == 0


def test_a_flood_of_requests_is_answered_at_the_rate_not_per_request():
    s = ParamStream(rate_hz=500, burst=32)
    sent = 0
    for tick in range(20):  # one second at 20 Hz, 75 requests a tick
        for _ in range(75):
            s.request((88, 190))
        sent += len(s.due(tick * 50_000, N))
    assert sent <= 32 + 500 * 0.95 + 1
    assert s.requests == 20 * 75 and s.restarted >= 20 * 74  # each request cost a dict update


def test_requesters_share_the_bucket_and_a_fifth_evicts_the_oldest():
    s = ParamStream(rate_hz=100, burst=4, max_streams=4)
    for sysid in (1, 2, 3, 4):
        s.request((sysid, 1))
    assert [r[0] for r, _ in s.due(0, N)] == [1, 2, 3, 4]
    s.request((5, 1))
    assert s.evicted == 1 and s.active == 4
    out = s.due(40_000, N)  # 4 tokens again
    assert [r[0] for r, _ in out] == [2, 3, 4, 5] and [i for _, i in out] == [1, 1, 1, 0]

"""Fuzz tier: hypothesis-generated command payloads through the daemon's real query path
(tecdard.intake.QueryIntake.handle: size check, bounded parse, validation, hand-over).

Each example is a batch of payloads, so that the suite sends over 1e5 of them (1800 examples of
60) in about a minute. Whatever the payload, the handler never raises, answers exactly once or hands the
control thread exactly one command, and an answer is one short line with a known code; a command
it hands on carries only finite values within the configured limits.
"""
import json
import math
import time

import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from tecdard.api import commands as C
from tecdard.runtime.intake import IntakeParams, QueryIntake
from tecdard.api.session import Keys

LIMITS = C.Limits(max_speed=0.05, min_speed=0.002, max_rotation_deg=90.0, max_probe_distance=0.02)
KEYS = Keys("sim")
CODES = {C.BAD_JSON, C.UNKNOWN_VERB, C.UNKNOWN_FIELD, C.MISSING_FIELD, C.BAD_TYPE, C.OUT_OF_LIMITS, C.BUSY,
         C.NO_TASK, C.FAULT, C.PAYLOAD_TOO_LARGE, C.RATE_LIMITED, C.BAD_REQUEST}
MAX_MESSAGE_CHARS = 400          # a refusal's message: one line, about the length of the longest we write
BATCH = 60                       # payloads per hypothesis example
FIELDS = {"probe": ("direction", "distance", "speed"),
          "rotate": ("angle_deg", "speed", "probe_distance", "direction", "strategy", "turn_tool"),
          "point": ("radius", "speed", "turns"),
          "approach": ("direction", "speed", "max_distance", "stop_angle_deg"),
          "map": ("origin", "size", "grid", "depth", "orientations", "speed"),
          "stop": (), "status": (), "cancel": ("task",)}
def fuzz_settings(examples: int) -> settings:
    return settings(max_examples=examples, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


class Sink:
    """Stands in for the control thread and for each query's reply channel: records, checks nothing."""

    def __init__(self):
        self.submitted, self.replies, self.accept = [], [], True

    def submit(self, msg) -> bool:
        if self.accept:
            self.submitted.append(msg)
        return self.accept

    def request_stop(self, msg) -> None:
        self.submitted.append(msg)


class Query:
    def __init__(self, key, sink):
        self.key_expr, self.sink = key, sink

    def reply(self, key, text, encoding=None):
        self.sink.replies.append(text)


def intake(sink):
    q = QueryIntake(KEYS, LIMITS, sink, lambda: '{"mode":"idle"}',
                    IntakeParams(max_task_rate_hz=1e9, max_status_rate_hz=1e9, max_other_rate_hz=1e9))
    return q


def check_one(q, sink, verb: str, payload: bytes) -> str:
    """Send one payload on cmd/<verb>, check what came of it, and say what that was: "stop" (left to
    the stop queryable), "answered" (status), "refused" or "handed" (to the control thread)."""
    n_sub, n_rep = len(sink.submitted), len(sink.replies)
    key = KEYS.cmd_prefix + verb
    q.handle(Query(key, sink), key, payload, 0.0)
    new_sub, new_rep = sink.submitted[n_sub:], sink.replies[n_rep:]
    if verb == "stop":
        assert not new_sub and not new_rep            # the stop queryable answers stops
        return "stop"
    assert len(new_sub) + len(new_rep) == 1, (verb, payload[:80], new_sub, new_rep)
    if new_rep:
        reply = json.loads(new_rep[0])
        if reply["ok"]:
            assert verb == "status"
            return "answered"
        err = reply["error"]
        assert err["code"] in CODES, err
        assert "\n" not in err["message"] and "\r" not in err["message"] and len(err["message"]) <= MAX_MESSAGE_CHARS, err
        assert err["code"] != C.BAD_REQUEST, err      # a bad_request is a bug of ours: none may show up here
        return "refused"
    fields = new_sub[0].fields if hasattr(new_sub[0], "fields") else {"task": new_sub[0].task}
    check_fields(verb, fields)
    return "handed"


def assert_accounted(outcomes: list[str], sink) -> None:
    """Every payload of a batch came to exactly one end: a reply or a hand-over (stops aside)."""
    assert set(outcomes) <= {"stop", "answered", "refused", "handed"}, outcomes
    assert len(sink.replies) == outcomes.count("answered") + outcomes.count("refused")
    assert len(sink.submitted) == outcomes.count("handed")


def check_fields(verb: str, f: dict) -> None:
    for name, v in f.items():
        if isinstance(v, float):
            assert math.isfinite(v), (name, v)
        if isinstance(v, list):
            assert all(math.isfinite(x) for x in v if isinstance(x, float)), (name, v)
    if "speed" in f:
        assert LIMITS.min_speed <= f["speed"] <= LIMITS.max_speed
    if "direction" in f:
        assert abs(math.hypot(*f["direction"]) - 1.0) < 1e-9
    if verb == "rotate":
        assert 0.1 <= f["angle_deg"] <= LIMITS.max_rotation_deg
        assert f["probe_distance"] <= LIMITS.max_probe_distance
    if verb == "map":
        assert f["grid"][0] * f["grid"][1] <= LIMITS.max_map_points and f["depth"] <= LIMITS.max_map_depth
    if verb == "cancel":
        assert f["task"] is None or (isinstance(f["task"], str) and len(f["task"]) <= C.MAX_TASK_ID_CHARS)


# -- strategies ------------------------------------------------------------------
def number_text():
    """Numbers as a sender may write them: ordinary, huge, tiny, long, and some that are no JSON at all."""
    return st.one_of(
        st.floats(allow_nan=False, allow_infinity=False).map(repr),
        st.integers(-10**6, 10**6).map(str),
        st.integers(min_value=300, max_value=6000).map(lambda n: "9" * n),          # 309+ and 4300+ digits
        st.integers(min_value=1, max_value=400).map(lambda n: f"1e{n}"),
        st.integers(min_value=1, max_value=400).map(lambda n: f"-1.5e-{n}"),
        st.sampled_from(["NaN", "Infinity", "-Infinity", "1e308", "1e309", "-0", "0.0", "1.", ".5", "01", "+1"]),
    )


def json_text(depth: int = 0):
    """JSON-ish text: valid values mixed with the number forms above, deep nesting and odd strings."""
    leaf = st.one_of(number_text(),
                     st.text(max_size=30).map(lambda s: json.dumps(s, ensure_ascii=False)),
                     st.sampled_from(["true", "false", "null", '"arc"', '"straight"', '"\\u0000"', '"\\ud800"']))
    return st.recursive(
        leaf,
        lambda inner: st.one_of(
            st.lists(inner, max_size=4).map(lambda xs: "[" + ",".join(xs) + "]"),
            st.lists(st.tuples(st.one_of(st.sampled_from(sorted({f for fs in FIELDS.values() for f in fs})),
                                         st.text(max_size=20)), inner), max_size=4)
            .map(lambda kv: "{" + ",".join(json.dumps(k) + ":" + v for k, v in kv) + "}")),
        max_leaves=12)


def command_text():
    """A command object for some verb: its own fields (or others) with fuzzed values."""
    return st.sampled_from(sorted(FIELDS)).flatmap(lambda verb: st.tuples(
        st.just(verb),
        st.dictionaries(st.one_of(st.sampled_from(FIELDS[verb] or ("x",)), st.text(max_size=70)),
                        json_text(), max_size=5)
        .map(lambda d: "{" + ",".join(json.dumps(k) + ":" + v for k, v in d.items()) + "}")))


def nested_text():
    return st.tuples(st.integers(1, 5000), st.sampled_from(["[", '{"a":'])).map(
        lambda t: t[1] * t[0] + "1" + ("]" if t[1] == "[" else "}") * t[0])


def verbs():
    return st.one_of(st.sampled_from(sorted(FIELDS)), st.text(max_size=80),
                     st.sampled_from(["stop/now", "rotate/x", "*", "**", "", "status/", "ROTATE"]))


payloads = st.one_of(
    command_text().map(lambda vt: (vt[0], vt[1].encode("utf-8", "surrogatepass"))),
    st.tuples(verbs(), json_text().map(lambda s: s.encode("utf-8", "surrogatepass"))),
    st.tuples(verbs(), nested_text().map(str.encode)),
    st.tuples(verbs(), st.binary(max_size=200)),                                  # not UTF-8, not JSON
    st.tuples(st.sampled_from(sorted(FIELDS)), st.integers(C.MAX_PAYLOAD_BYTES - 8, 4 * C.MAX_PAYLOAD_BYTES)
              .map(lambda n: b'{"angle_deg": ' + b"1" * n + b"}")),
)


# Hypothesis draws each payload of the structured test above value by value (about 10 ms a payload
# here), too slow for 1e5. The main tier lets hypothesis draw, per example, a template, a short
# program of mutations and a seed, and expands them into BATCH payloads with cheap byte-level
# mutations: hypothesis still chooses (and shrinks) what is sent, at about 0.1 ms a payload.
TEMPLATES = [
    ("rotate", '{"angle_deg": 30, "speed": 0.01, "probe_distance": 0.004, "direction": [0, 0, 1], '
               '"strategy": "arc", "turn_tool": true}'),
    ("rotate", '{"angle_deg": 30}'),
    ("probe", '{"direction": [0.0, 0.6, 0.8], "distance": 0.005, "speed": 0.01}'),
    ("point", '{"radius": 0.01, "speed": 0.01, "turns": 1.5}'),
    ("approach", '{"direction": [0, 0, -1], "speed": 0.01, "max_distance": 0.1, "stop_angle_deg": 5}'),
    ("map", '{"origin": [0.3, -0.1], "size": [0.1, 0.1], "grid": [3, 4], "depth": 0.05, "orientations": 2, '
            '"speed": 0.01}'),
    ("cancel", '{"task": "rotate-1234abcd"}'),
    ("status", ""), ("stop", "{}"), ("rotate", '{"angle_deg": 99999999999999999999999999999999999999}'),
    ("probe", '{"direction": [1e308, 1e308, 0]}'), ("rotate", "[" * 40 + "]" * 40),
]
NUMBER_FORMS = [b"9" * 309, b"9" * 4301, b"1e400", b"-1e400", b"NaN", b"Infinity", b"1e308", b"-0", b"0",
                b"1e-400", b"0.5", b"-3", b"true", b"null", b'"30"', b"[]", b"{}", b"[1,2,3]",
                rb'"\u0000"', rb'"\ud800"', b'"' + b"x" * 5000 + b'"']
KEY_FORMS = [rb'"a\nb"', b'"a\nb"', b'"' + b"k" * 1000 + b'"', b'""', b'"angle_deg"', b'"speed"', b'"direction"',
             rb'"\u202e"', b'"grid"', b'"task"', b'"__proto__"']
VERB_FORMS = sorted(FIELDS) + ["stop/now", "rotate/x", "*", "**", "", "ROTATE", "r\no", "x" * 200]


def mutate(data: bytes, rng, raw: bytes) -> bytes:
    """One random byte-level or token-level change of a payload."""
    op = rng.randrange(10)
    n = len(data)
    i = rng.randrange(n + 1)
    j = min(n, i + rng.randrange(1, 40))
    if op == 0:                                   # a number or literal becomes another form
        return data[:i] + rng.choice(NUMBER_FORMS) + data[j:]
    if op == 1:                                   # a key becomes a hostile one
        return data[:i] + rng.choice(KEY_FORMS) + b":" + rng.choice(NUMBER_FORMS) + b"," + data[i:]
    if op == 2:                                   # bytes from hypothesis spliced in
        return data[:i] + raw + data[i:]
    if op == 3:                                   # a range deleted
        return data[:i] + data[j:]
    if op == 4:                                   # a range repeated
        return data[:j] + data[i:j] * rng.randrange(2, 6) + data[j:]
    if op == 5:                                   # wrapped in deep nesting
        d = rng.choice([3, 31, 33, 1000, 5000])
        return b"[" * d + data + b"]" * d
    if op == 6:                                   # cut short
        return data[:i]
    if op == 7:                                   # one byte flipped
        return data[:i] + bytes([rng.randrange(256)]) + data[i + 1:]
    if op == 8:                                   # a value made a deep structure
        d = rng.choice([2, 40, 2000])
        return data[:i] + b'{"a":' * d + b"1" + b"}" * d + data[j:]
    return data[:i] + b"\\" * rng.randrange(1, 9) + b'"' + data[i:]    # escapes and quotes


@pytest.mark.slow
@fuzz_settings(1800)
@given(st.sampled_from(range(len(TEMPLATES))), st.sampled_from(range(len(VERB_FORMS) + 8)),
       st.integers(0, 2 ** 32 - 1), st.binary(max_size=48), st.integers(1, 6))
def test_any_payload_is_answered_once_or_handed_on_within_limits(template, verb_choice, seed, raw, depth):
    import random
    rng = random.Random(seed)
    base_verb, text = TEMPLATES[template]
    sink = Sink()
    q = intake(sink)
    outcomes = []
    for _ in range(BATCH):
        data = text.encode()
        for _ in range(rng.randrange(1, depth + 1)):
            data = mutate(data, rng, raw)
        verb = base_verb if verb_choice >= len(VERB_FORMS) else VERB_FORMS[verb_choice]
        outcomes.append(check_one(q, sink, verb, data))
    assert len(outcomes) == BATCH
    assert_accounted(outcomes, sink)


@pytest.mark.slow
@fuzz_settings(60)
@given(st.lists(payloads, min_size=10, max_size=10))
def test_structured_payloads_are_answered_once_or_handed_on_within_limits(batch):
    sink = Sink()
    q = intake(sink)
    outcomes = [check_one(q, sink, verb, payload) for verb, payload in batch]
    assert_accounted(outcomes, sink)


@pytest.mark.slow
@fuzz_settings(20)
@given(st.lists(command_text(), min_size=10, max_size=10))
def test_a_full_control_queue_is_a_busy_reply_not_a_lost_command(batch):
    sink = Sink()
    sink.accept = False
    q = intake(sink)
    for verb, text in batch:
        n = len(sink.replies)
        key = KEYS.cmd_prefix + verb
        q.handle(Query(key, sink), key, text.encode("utf-8", "surrogatepass"), 0.0)
        if verb != "stop":
            assert len(sink.replies) == n + 1
    assert q.pending == 0          # nothing stays registered for a command that was never handed on


@pytest.mark.parametrize("payload,code", [
    (b'{"angle_deg": ' + b"9" * 309 + b"}", C.BAD_JSON),
    (b'{"angle_deg": ' + b"9" * 4301 + b"}", C.BAD_JSON),
    (b'{"angle_deg": 30, "direction": [1e308, 1e308, 0]}', C.OUT_OF_LIMITS),
    (b"[" * 1000 + b"]" * 1000, C.BAD_JSON),
    (b"\xff\xfe{}", C.BAD_JSON),
    (b" " * (C.MAX_PAYLOAD_BYTES + 1), C.PAYLOAD_TOO_LARGE),
])
def test_the_red_team_crashes_are_refused(payload, code):
    sink = Sink()
    q = intake(sink)
    key = KEYS.cmd("rotate")
    q.handle(Query(key, sink), key, payload, 0.0)
    assert not sink.submitted
    assert json.loads(sink.replies[0])["error"]["code"] == code


def test_names_are_escaped_and_cut_in_replies():
    sink = Sink()
    q = intake(sink)
    key = KEYS.cmd("rotate")
    for name in ("a\nb", "x" * 1_000):
        q.handle(Query(key, sink), key, json.dumps({"angle_deg": 30, name: 1}).encode(), 0.0)
    forged, long_ = (json.loads(r)["error"]["message"] for r in sink.replies)
    assert "\n" not in forged and "a\\nb" in forged
    assert len(long_) < 200 and "..." in long_
    q.handle(Query(KEYS.cmd("stop/now"), sink), KEYS.cmd("stop/now"), b"", 0.0)
    assert json.loads(sink.replies[-1])["error"]["code"] == C.UNKNOWN_VERB


def test_over_the_rate_a_query_is_refused_then_dropped():
    sink = Sink()
    q = QueryIntake(KEYS, LIMITS, sink, lambda: "{}", IntakeParams(max_status_rate_hz=10.0))
    key = KEYS.cmd("status")
    now = time.monotonic()
    for _ in range(700):
        q.handle(Query(key, sink), key, b"", now)           # all in one instant
    codes = [json.loads(r).get("error", {}).get("code") for r in sink.replies]
    assert codes[:10] == [None] * 10                         # a second's worth is served at once
    assert set(codes[10:]) == {C.RATE_LIMITED}
    rotate = KEYS.cmd("rotate")                              # the status flood costs other classes nothing
    q.handle(Query(rotate, sink), rotate, b'{"angle_deg": 10}', now)
    assert sink.submitted and sink.submitted[-1].verb == "rotate"
    assert q.counters["dropped"] > 0 and len(sink.replies) < 700    # the refusals have a budget too
    q.handle(Query(key, sink), key, b"", now + 1.0)          # a second later the rate allows more
    assert json.loads(sink.replies[-1])["ok"] is True


class Ring:
    def __init__(self, queries):
        self.queries = list(queries)

    def try_recv(self):
        return self.queries.pop(0) if self.queries else None


def test_copies_of_known_verbs_in_the_catch_all_ring_are_dropped_whatever_the_budget():
    """cmd/** sees a copy of every query to a known verb, and a querier's default consolidation holds
    the replies back until each copy is dropped: under a flood a copy left waiting delayed stop's
    reply by 100-250 ms. The catch-all ring is drained on every pass, its copies unanswered."""
    sink = Sink()
    q = QueryIntake(KEYS, LIMITS, sink, lambda: "{}", IntakeParams(max_other_rate_hz=1.0))
    q._parse["other"].tokens = 0.0
    q._refuse.tokens = 0.0
    copies = [Query(KEYS.cmd("status"), sink) for _ in range(5)] + [Query(KEYS.cmd("stop"), sink)]
    q._rings = [("other", Ring(copies))]
    assert q.poll(time.monotonic()) == 6
    assert sink.replies == [] and sink.submitted == []

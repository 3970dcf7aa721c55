"""The simulated robot: requests in order, answers recorded, pacing, and the call order enforced."""

from __future__ import annotations

import time

import pytest

from sofast_station.devices.protocols import FAULT_CODES, FacetRequest
from sofast_station.devices.triggers.simulated import SimulatedRobot
from sofast_station.errors import TriggerError


def _cycle(robot: SimulatedRobot, answer=("done", "pass"), timeout_s: float = 1.0) -> FacetRequest:
    robot.ready()
    request = robot.wait_for_facet(timeout_s)
    assert request is not None
    robot.busy()
    if answer[0] == "done":
        robot.done(answer[1])
    else:
        robot.fault(*answer[1:])
    return request


def test_int_makes_numbered_serials_and_every_answer_is_recorded():
    robot = SimulatedRobot(3)
    assert [r.serial for r in robot.requests] == ["SIM-0001", "SIM-0002", "SIM-0003"]
    answers = [("done", "pass"), ("fault", FAULT_CODES["camera"], "camera timeout"), ("done", "invalid")]
    served = []
    for i, answer in enumerate(answers):
        assert not robot.finished
        served.append(_cycle(robot, answer).serial)
        robot.heartbeat()
    assert served == ["SIM-0001", "SIM-0002", "SIM-0003"]
    assert robot.finished
    kinds = [(a.serial, a.kind, a.verdict, a.code) for a in robot.answers]
    assert kinds == [("SIM-0001", "busy", None, None), ("SIM-0001", "done", "pass", None),
                     ("SIM-0002", "busy", None, None), ("SIM-0002", "fault", None, 2),
                     ("SIM-0003", "busy", None, None), ("SIM-0003", "done", "invalid", None)]
    assert robot.answers[3].reason == "camera timeout"
    times = [a.time_s for a in robot.answers]
    assert times == sorted(times)
    assert len(robot.heartbeats) == 3
    # Nothing more to hand out: an idle line returns None after the timeout.
    robot.ready()
    t0 = time.monotonic()
    assert robot.wait_for_facet(0.05) is None
    assert time.monotonic() - t0 >= 0.045
    robot.close()


def test_given_requests_come_in_order_with_their_details():
    reqs = [FacetRequest("A-1", recipe="gore", dump=True, extra={"k": 1}), FacetRequest("A-2")]
    robot = SimulatedRobot(reqs)
    assert _cycle(robot) is reqs[0]
    assert _cycle(robot, ("done", "fail")) is reqs[1]
    assert robot.finished


def test_period_paces_the_facets_and_wait_times_out_before_the_next_is_due():
    robot = SimulatedRobot(3, period_s=0.15)
    robot.ready()
    t0 = time.monotonic()
    got = []
    for _ in range(3):
        request = None
        while request is None:
            request = robot.wait_for_facet(0.05)  # shorter than the period: some calls return None
            if request is None:
                robot.heartbeat()
        got.append(time.monotonic() - t0)
        robot.busy()
        robot.done("pass")
        robot.ready()
    assert got[0] < 0.05
    assert got[1] >= 0.14 and got[2] >= 0.29
    assert len(robot.heartbeats) >= 4


@pytest.mark.parametrize("calls", [
    ["busy"],                                   # busy without a request
    ["ready", "busy"],
    ["ready", "wait", "done"],                  # done without busy
    ["ready", "wait", "busy", "done", "done"],  # answered twice
    ["wait"],                                   # waiting before ready
    ["ready", "wait", "ready"],                 # ready while a request is pending
])
def test_calls_out_of_order_raise_trigger_error(calls):
    robot = SimulatedRobot(2)
    do = {"ready": robot.ready, "wait": lambda: robot.wait_for_facet(0.1), "busy": robot.busy,
          "done": lambda: robot.done("pass")}
    for call in calls[:-1]:
        do[call]()
    with pytest.raises(TriggerError, match="protocol violation"):
        do[calls[-1]]()


def test_bad_arguments_and_closed_robot():
    robot = SimulatedRobot(1)
    robot.ready()
    robot.wait_for_facet(0.1)
    robot.busy()
    with pytest.raises(ValueError, match="verdict"):
        robot.done("ok")
    with pytest.raises(ValueError, match="fault code"):
        robot.fault(0, "no code")
    robot.close()
    with pytest.raises(TriggerError, match="closed"):
        robot.heartbeat()


def test_fail_ack_raises_after_recording_and_reopen_continues_the_line():
    robot = SimulatedRobot(3, fail_ack=[1])
    _cycle(robot)
    robot.ready()
    robot.wait_for_facet(0.1)
    robot.busy()
    with pytest.raises(TriggerError, match="did not acknowledge"):
        robot.done("fail")
    assert robot.answers[-1].serial == "SIM-0002" and robot.answers[-1].verdict == "fail"
    robot.close()
    robot.reopen()
    assert _cycle(robot).serial == "SIM-0003"
    assert robot.finished


def test_reopen_places_an_unanswered_facet_again():
    robot = SimulatedRobot(2)
    robot.ready()
    assert robot.wait_for_facet(0.1).serial == "SIM-0001"
    robot.busy()
    robot.close()  # e.g. the station's cycle died before it answered
    robot.reopen()
    assert _cycle(robot).serial == "SIM-0001"
    assert _cycle(robot).serial == "SIM-0002"
    assert robot.finished

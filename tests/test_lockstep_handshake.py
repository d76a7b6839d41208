"""The pieces that make a lock-step simulation repeat exactly: the base station waits for
what each robot's command says it sent, the agent waits for what the base station's
mark says it sent, and a drone's sensor messages arrive in the order they were sent."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

from agent.downlink_gate import DownlinkGate
from agent.sensor_sources import ZenohSensors
from basestation.lockstep import LockstepClock
from common.bus import Bus
from common.config import ZenohConfig
from common.geometry import pose4_to_pose7
from protocol import (
    Altimeter,
    ClockSync,
    DownlinkMark,
    Imu,
    LaserScan,
    Odometry,
    VehicleCommand,
)

TOPICS = {
    Odometry: "odom",
    Imu: "imu",
    Altimeter: "altimeter",
    LaserScan: "scan",
    ClockSync: "clock",
}


def _later(delay_s: float, fn, *args) -> threading.Thread:
    t = threading.Thread(target=lambda: (time.sleep(delay_s), fn(*args)))
    t.start()
    return t


def test_gate_holds_a_tick_until_the_marked_downlink_is_in() -> None:
    gate = DownlinkGate(timeout_s=10.0)
    gate.wait()  # no lock-step simulator yet: nothing to wait for
    assert gate.waits == 0
    gate.on_clock(1.0)  # the simulator: the base station answered t = 1
    gate.on_mark(DownlinkMark("r0", 1.0, paths=2, epoch=5))  # the mark overtook them
    arrived: list[str] = []
    threads = [
        _later(0.1, lambda: (arrived.append("path"), gate.on_path())),
        _later(0.2, lambda: (arrived.append("path"), gate.on_path())),
        _later(0.3, lambda: (arrived.append("correction"), gate.on_correction(5))),
    ]
    gate.wait()
    assert sorted(arrived) == ["correction", "path", "path"] and gate.waits == 1
    for t in threads:
        t.join()
    gate.state_sent(1.2)  # the next state: its neighbours' answer is awaited too
    _later(0.1, gate.on_neighbours, 1.2).join(0.0)
    gate.wait()
    assert gate.timeouts == 0


def test_gate_gives_up_after_its_timeout_and_goes_on() -> None:
    gate = DownlinkGate(timeout_s=0.2)
    gate.on_clock(2.0)  # no mark will come
    t0 = time.monotonic()
    gate.wait()
    assert gate.timeouts == 1 and time.monotonic() - t0 >= 0.2
    gate.wait()  # until the simulator's next word it does not wait again
    assert gate.timeouts == 1
    gate.on_clock(3.0)
    gate.on_mark(DownlinkMark("r0", 3.0, paths=0, epoch=-1))
    gate.state_sent(3.0)  # never answered: stops waiting for neighbours after one timeout
    gate.wait()
    gate.wait()
    assert gate.timeouts == 2


def test_clock_waits_for_everything_a_command_says_was_sent() -> None:
    clock = LockstepClock(active=True, timeout_s=60.0)
    have = {"r0": (2, 0.8)}  # keyframes received, latest state's stamp
    clock.on_command(VehicleCommand("r0", 1.0, 0, 0, 0, 0, keyframes_sent=3, state_stamp=1.0), "")
    seen = []  # what the clock read each time it looked
    _later(0.2, have.__setitem__, "r0", (3, 1.0))
    assert clock.wait_inputs(1.0, ["r0"], lambda r: seen.append(have[r]) or have[r], 10.0) == []
    # it went on only once the third keyframe and the state of t = 1 were in
    assert seen[0] == (2, 0.8) and seen[-1] == (3, 1.0) and (3, 1.0) not in seen[:-1]
    # a robot that has not commanded at the stamp is named after the timeout
    assert clock.wait_inputs(1.0, ["r0", "r1"], lambda r: have.get(r, (0, -1.0)), 0.1) == ["r1"]
    # what went down to each robot, for its mark
    clock.sent_path("r0")
    clock.sent_path("r0")
    clock.sent_correction("r0", 7)
    marks = [clock.mark(r, 1.0) for r in ("r0", "r1")]
    assert [(m.robot_id, m.stamp, m.paths, m.epoch) for m in marks] == [
        ("r0", 1.0, 2, 7),
        ("r1", 1.0, 0, -1),
    ]


def test_a_drones_sensor_messages_arrive_in_the_order_they_were_sent(endpoint: str) -> None:
    """One subscriber for all of a drone's sensor topics: with one per topic, a scan
    overtook the altimeter reading published just before it (Zenoh keeps a sender's
    order per subscriber only)."""
    with (
        Bus(ZenohConfig(listen=[endpoint]), "default") as sim,
        Bus(ZenohConfig(connect=[endpoint]), "default") as agent,
    ):
        # (7.5 s of sensor time sent before any is taken: no lag limit here)
        source = ZenohSensors(agent, "r0", max_scans_before_altitude=0, max_scan_lag_s=0.0)
        time.sleep(0.5)
        sent = []
        pose = pose4_to_pose7([0.0, 0.0, 1.0, 0.0])
        q = np.array([0.0, 0.0, 0.0, 1.0])
        for k in range(300):
            t = k * 0.025
            for msg in (
                Odometry("r0", t, pose, np.zeros(4)),
                Imu("r0", t, np.zeros(3), np.zeros(3), q),
                Altimeter("r0", t, 1.0),
                LaserScan("r0", t, -1.0, 0.01, 0.1, 30.0, np.ones(200, np.float32)),
                ClockSync("sim", t),
            ):
                sim.publish(sim.keys.sensor("r0", TOPICS[type(msg)]), msg)
                sent.append((type(msg).__name__, t))
        stop = threading.Event()
        got, idle = [], 0
        for msg in source.messages(stop):
            idle = idle + 1 if msg is None else 0
            if idle == 40 or len(got) == len(sent):  # (2 s of nothing: a loaded machine
                break  # may pause the delivery for more than one 50 ms idle)
            if msg is not None:
                got.append((type(msg).__name__, msg.stamp))
        assert got == sent


def test_a_clock_stamped_far_ahead_is_held_back() -> None:
    """A ClockSync of 1e9 s on clock/sim had been answered, and every real request after it
    taken as answered already (the simulator hung); on a drone's sensor key it had every
    tick wait for a mark that would never come."""
    clock = LockstepClock(active=True, timeout_s=60.0)
    clock.on_request(ClockSync("sim", 1e9), "")
    assert clock.wait_request(0.0) is None
    clock.on_request(ClockSync("sim", 0.2), "")
    assert clock.wait_request(0.0) == 0.2
    gate = DownlinkGate(timeout_s=0.2)
    gate.on_clock(1e9)
    gate.on_clock(1.0)
    gate.on_mark(DownlinkMark("r0", 1.0, paths=0, epoch=-1))
    gate.wait()
    assert gate.timeouts == 0
    gate.on_clock(70.0)  # a real jump (the next follows it): taken
    gate.on_clock(70.2)
    gate.on_mark(DownlinkMark("r0", 70.2, paths=0, epoch=-1))
    gate.wait()
    assert gate.timeouts == 0


def test_a_simulator_gone_before_its_first_request_frees_the_verifier() -> None:
    """Ctrl-C early in `collabslam run`: the simulator left before the base station had
    answered a request, and its drain waited out the 60 s start timeout for a match."""
    clock = LockstepClock(active=True, timeout_s=60.0)
    now = time.monotonic()
    assert not clock.verify_on_worker(now)
    clock.on_sim_alive("sim", False)
    assert clock.verify_on_worker(now)


def test_a_fix_count_or_command_far_ahead_is_held_back() -> None:
    """A request counting 2^63 GNSS fixes had every later sync wait 10 s for them; a
    command stamped 1e300 s stayed its robot's latest for good (nothing waited for)."""
    clock = LockstepClock(active=True, timeout_s=60.0)
    clock.takes_fixes = True
    clock.on_request(ClockSync("sim", 1.0, gnss_fixes=2**63), "")
    clock.on_command(VehicleCommand("r0", 1e300, 0, 0, 0, 0, keyframes_sent=0), "")
    clock.on_command(VehicleCommand("r0", 1.0, 0, 0, 0, 0, keyframes_sent=7, state_stamp=1.0), "")
    got = {"r0": (0, -1.0)}
    assert clock.wait_inputs(1.0, ["r0"], got.get, 0.05) == ["r0"]  # its 7 keyframes
    got["r0"] = (7, 1.0)
    assert clock.wait_inputs(1.0, ["r0"], got.get, 10.0) == []  # and no fix count
    assert clock.input_timeouts == 1  # (summary.json's lockstep_timeouts counts it)


def test_a_resumed_agent_does_not_wait_for_what_went_to_the_one_before() -> None:
    """An agent restarted mid-mission (agent.state_dir): the base station's marks count
    the paths sent to the agent before it, which this one never gets. It had waited
    10 s at every step (a mission at 0.14x real time)."""
    from agent.downlink_gate import DownlinkGate
    from protocol import DownlinkMark

    for resumed, timeouts in ((True, 0), (False, 1)):
        gate = DownlinkGate(0.2, resumed=resumed)
        gate.on_mark(DownlinkMark("r1", 11.0, 9, 23))  # 9 paths, epoch 23 sent before
        gate.on_clock(11.0)
        gate.wait()
        assert gate.timeouts == timeouts
        gate.on_mark(DownlinkMark("r1", 12.0, 10, 25))  # a new path and correction
        gate.on_clock(12.0)
        gate.on_path()
        gate.on_correction(25)
        gate.wait()
        assert gate.timeouts == 2 * timeouts  # counted on from the first mark (or never in)


def test_a_mark_or_a_simulated_command_far_ahead_is_held_back(endpoint: str) -> None:
    """A DownlinkMark stamped 1e9 s (counting 10^6 paths) had been kept as the latest for
    good: every tick waited out the timeout. A VehicleCommand stamped 1e9 s had become the
    simulator's answered stamp: every later command was dropped as an old answer, and
    the drone flew the glitch's velocity on."""
    from common.config import load_config
    from common.scenario import RobotScenario, Scenario
    from simulation.simulator import Simulator
    from simulation.world import World

    gate = DownlinkGate(timeout_s=0.2)
    gate.on_mark(DownlinkMark("r0", 1e9, 10**6, 0))
    for t in (1.0, 2.0):
        gate.on_mark(DownlinkMark("r0", t, 0, -1))
        gate.on_clock(t)
        gate.wait()
    assert gate.timeouts == 0
    cfg = load_config(overrides={"exploration.enabled": False})
    sc = Scenario("rooms15", [RobotScenario("r0", np.array([1.5, 2.5, 0.0]))])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        sim._on_command(VehicleCommand("r0", 0.025, 0.5, 0.0, 0.0, 0.0), "")
        sim._on_command(VehicleCommand("r0", 1e9, 1.0, 0.0, 0.0, 0.0), "")
        sim._on_command(VehicleCommand("r0", 0.05, 0.0, 0.0, 0.0, 0.0), "")  # stop
        assert sim.robots["r0"].command[0] == 0.0 and sim.robots["r0"].answered == 0.05


def test_a_simulated_drone_whose_agent_went_silent_hovers(endpoint: str) -> None:
    """The simulator, the docs' example driver, had held the last command for good: an
    agent killed in flight had its drone fly on at 1 m/s into a wall 5.8 s later. No
    answer for `COMMAND_TIMEOUT_S` of sim time: it hovers."""
    from common.config import load_config
    from common.scenario import RobotScenario, Scenario
    from simulation.simulator import COMMAND_TIMEOUT_S, Simulator
    from simulation.world import World

    cfg = load_config(overrides={"exploration.enabled": False})
    sc = Scenario("rooms15", [RobotScenario("r0", np.array([1.5, 2.5, 0.0]))])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        sim._on_command(VehicleCommand("r0", 0.0, 0.5, 0.0, 0.0, 0.0), "")
        speeds = []
        for k in range(1, 40):  # the agent answered t = 0 and no tick after
            sim.t = k * sim.dt
            sim._step_physics()
            speeds.append(float(np.hypot(*sim.robots["r0"].vehicle.velocity_world[:2])))
    late = int(COMMAND_TIMEOUT_S / sim.dt) + 1
    assert speeds[late - 2] > 0.1 and speeds[-1] < 0.01  # flew on the answer, then stopped
    cfg.sim.laser.rate_hz = 3.0  # a tick longer than the timeout, each one answered
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        for k in range(1, 6):
            sim._on_command(VehicleCommand("r0", (k - 1) * sim.dt, 0.5, 0.0, 0.0, 0.0), "")
            sim.t = k * sim.dt
            sim._step_physics()
        assert np.hypot(*sim.robots["r0"].vehicle.velocity_world[:2]) > 0.4  # (it had hovered)


def test_a_real_time_exploring_clock_waits_for_the_base_station(endpoint: str) -> None:
    """In real time the simulator had started its clock as soon as the agents were up:
    the base station heard of the drones 2.5-14.5 s later (they hovered), and one was
    planned through another's hover point. Like lock-step, it waits for the base."""
    from common.config import load_config
    from common.scenario import RobotScenario, Scenario
    from simulation.simulator import Simulator
    from simulation.world import World

    cfg = load_config(overrides={"sim.clock": "realtime", "sim.start_timeout_s": 3.0})
    sc = Scenario("rooms15", [RobotScenario("r0", np.array([1.5, 2.5, 0.0]))])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        sim.start()
        sim._on_alive("r0", True)  # the agent is up; no base station anywhere
        stop, started = threading.Event(), threading.Event()

        def run() -> None:
            with contextlib.suppress(Exception):
                sim.wait_for_agents(stop)
                started.set()

        th = threading.Thread(target=run, daemon=True)
        th.start()
        th.join(1.0)
        assert not started.is_set()
        sim._on_base_alive("basestation", True)
        th.join(2.0)
        stop.set()
    assert started.is_set()


def test_a_tick_sent_again_leaves_out_its_gnss_fix(endpoint: str) -> None:
    """A tick re-published to an agent slower than `sim.lockstep_timeout_s` (a cold numba
    cache) had carried its GNSS fix again: the base station took the fix at t = 0 four
    times (four times its weight in the graph), and a cold run and a warm one of one
    seed flew apart."""
    from common.config import load_config
    from common.scenario import RobotScenario, Scenario
    from protocol import GnssFix, encode
    from simulation.simulator import Simulator
    from simulation.world import World

    cfg = load_config(overrides={"exploration.enabled": False})
    sc = Scenario("rooms15", [RobotScenario("r0", np.array([1.5, 2.5, 0.0]))])
    got: list[object] = []
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        bus.subscribe(
            bus.keys.robot("r0", "sensor/*"), (GnssFix, Altimeter), lambda m, k: got.append(m)
        )
        time.sleep(0.2)
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        fix = GnssFix("r0", 0.0, np.array([45.8, 16.0, 160.0]), np.array([1.5, 1.5, 3.0]))
        sim.robots["r0"].tick = [
            (bus.keys.sensor("r0", "gnss"), encode(fix)),
            (bus.keys.sensor("r0", "altimeter"), encode(Altimeter("r0", 0.0, 1.0))),
        ]
        sim._late([sim.robots["r0"]])  # no command yet: the tick again
        deadline = time.monotonic() + 5.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.3)
    assert [type(m).__name__ for m in got] == ["Altimeter"]


def test_a_tick_sent_again_to_several_agents_is_one_line(endpoint: str, caplog) -> None:  # noqa: ANN001
    """Agents slow to answer a tick (a cold numba cache: 20 s at the first scans) are
    named on one line a wait, not one line each (12 lines for 3 drones, 4 waits)."""
    from common.config import load_config
    from common.scenario import RobotScenario, Scenario
    from simulation.simulator import Simulator
    from simulation.world import World

    cfg = load_config(overrides={"exploration.enabled": False})
    starts = [np.array([1.5 + i, 2.5, 0.0]) for i in range(3)]
    sc = Scenario("rooms15", [RobotScenario(f"r{i}", s) for i, s in enumerate(starts)])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        sim._late(list(sim.robots.values()))
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert warned == ["t=0.000: no command yet from r0, r1, r2; re-publishing the tick"]
    assert sim.republished == 3


def test_an_agents_stop_leaves_the_simulators_status_of_it(endpoint: str) -> None:
    """An agent's last state as it stops (`stopped`, for the base station's log) does not
    undo its `done`: the simulator still ends the mission when the others are done."""
    from common.config import load_config
    from common.scenario import RobotScenario, Scenario
    from protocol import RobotState
    from simulation.simulator import Simulator
    from simulation.world import World

    cfg = load_config(overrides={"exploration.enabled": False})
    sc = Scenario("rooms15", [RobotScenario("r0", np.array([1.5, 2.5, 0.0]))])
    pose = np.array([1.5, 2.5, 0.0, 0.0, 0.0, 0.0, 1.0])
    with Bus(ZenohConfig(listen=[endpoint]), cfg.fleet) as bus:
        sim = Simulator(cfg, bus, sc, World.load("rooms15"), 10.0)
        for status in ("done", "stopped"):
            sim._on_state(RobotState("r0", 1.0, status, 0, 5, 5, 0, pose, pose), "")
    assert sim.robots["r0"].status == "done"

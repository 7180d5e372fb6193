"""Flying a pollination plan on any bot, and resuming one that was interrupted.

The executor flies the visits of a `PollinationPlan` (`flights/pollination_plan.py`) in
order on any `Bot`: the physical one on serial or through FarmBot's web app, or a simulated one in
the harness (`eval/pollination/visits.py`), so what the harness scores is what a bot is told to
do. Before anything moves, every pose of the plan is checked against the connected bot's
own travel and head limits, and its position must be known (homed). Each visit starts
from the top of Z where the bot stands: up, across, the head turned, down to the
pre-approach pose (straight, or along the visit's path round the plant, the head turning at
its waypoints), in to the flower's centre, a rest, back out (and up the path).

After every visit `flight.json` records, atomically, which flowers were pollinated and
when on the bot's clock, so a flight cut short (an error, Ctrl-C, a dropped link) resumes
at the next visit instead of starting over; the visit it was cut in is flown again
(touching a flower twice does it no harm). Metres and radians, bed frame.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from flowerpose.errors import InputError
from flowerpose.hardware.bot import Bot, check_head, check_target
from flowerpose.hardware.flights.close_look import CloseLook
from flowerpose.hardware.flights.flight_journal import Journal, folder_lock
from flowerpose.hardware.flights.pollination_plan import Move, PollinationPlan
from flowerpose.hardware.kinematics import head_angles
from flowerpose.log import LOG, Tally

FLIGHT_NAME = "flight.json"
"""The flight's record in its folder: the plan's fingerprint, the visits done, sessions."""


def flight_id(plan: PollinationPlan) -> str:
    """A short fingerprint of the plan's moves, so a resume never mixes two plans."""
    values = np.concatenate([[m.flower, *m.pose.gantry, m.pose.yaw, m.pose.pitch]
                             for m in plan.moves] or [np.zeros(0)])
    return hashlib.sha1(np.round(values, 6).tobytes()).hexdigest()[:16]


def visit_moves(plan: PollinationPlan) -> dict[int, list[Move]]:
    """Each planned flower's moves after its lift (travel, descent, approach, rest,
    retreat), in the order flown."""
    moves: dict[int, list[Move]] = {}
    for move in plan.moves:
        if move.flower >= 0 and move.kind != "lift":
            moves.setdefault(move.flower, []).append(move)
    return moves


def check_flight(bot: Bot, plan: PollinationPlan) -> None:
    """Refuse, before anything moves, a plan the connected bot cannot fly: a pose outside
    its own travel or its servos' range (the plan was checked against the geometry it was
    planned for, which may not be this bot's), or a bot whose position is unknown."""
    here = bot.position()
    if not np.all(np.isfinite(here)):
        raise InputError(bot.info.name, "the gantry's position is unknown: home the bot "
                         "before pollinating")
    for move in plan.moves:
        where = f"flower {move.flower} ({move.kind})" if move.flower >= 0 else move.kind
        try:
            check_target(bot.info, move.pose.gantry)
            check_head(bot.info, *head_angles(move.pose))
        except InputError as error:
            raise InputError(f"{where}", f"{bot.info.name} cannot fly the plan: "
                             f"{error}") from None


#: Held (flock) by the one flight flying from a folder; the OS lets go when it dies.
LOCK_NAME = ".flight.lock"

#: What the record says when it belongs to another plan.
OTHER_PLAN = ("records the flight of another plan (other flowers, settings or cloud); "
              "choose a new folder")


def read_flight(out_dir: Path, plan: PollinationPlan) -> dict | None:
    """The flight of `plan` recorded in out_dir (None: none yet); one of another plan is
    refused, so a resume never mixes two plans."""
    return Journal.read(Path(out_dir) / FLIGHT_NAME, flight_id(plan), OTHER_PLAN)


def fly_pollination(bot: Bot, plan: PollinationPlan, out_dir: Path, *, source: dict,
                    progress: bool = True, look: CloseLook | None = None) -> dict:
    """Fly `plan` with `bot`, recording into out_dir/flight.json (`flight_journal`); resumes
    a flight of the same plan already recorded there, and refuses a folder another flight
    is flying from. With `look`, each visit looks again at its flower from the
    pre-approach pose and flies the approach planned from what it sees (`close_look.py`).
    Returns flight.json's content: `done`, one entry a visit flown ({"flower", "t0", "t1",
    "rest"}: bot-clock seconds from its lift to its way out's end, and of the swab's rest,
    null where it touched nothing; with a look its record, `look`), `status` ("complete",
    or "interrupted" when an error cut it), `sessions`."""
    out_dir = Path(out_dir)
    with folder_lock(out_dir, LOCK_NAME, "pollination flight"):
        return _fly(bot, plan, out_dir, source, progress, look)


def _fly(bot: Bot, plan: PollinationPlan, out_dir: Path, source: dict, progress: bool,
         look: CloseLook | None) -> dict:
    order = [v.flower for v in plan.planned]
    journal = Journal.open(out_dir / FLIGHT_NAME, flight_id(plan),
                           {"source": source, "visits": order, "done": []}, kept=("done",),
                           other_plan=OTHER_PLAN,
                           redone="the visit it was cut in is flown again")
    flight = journal.record
    done = {int(entry["flower"]) for entry in flight["done"]}
    pending = [flower for flower in order if flower not in done]
    if not pending:
        flight["status"] = "complete"
        if progress:
            LOG.info(f"pollinate: {journal.path} holds this plan's flight, complete: nothing "
                     "flown (choose a new folder to fly it again)")
        return flight
    check_flight(bot, plan)
    if done and progress:
        LOG.info(f"pollinate: resuming at visit {len(done) + 1} of {len(order)}"
                 + (" (the last session ended without closing)" if journal.cut else ""))
    moves = visit_moves(plan)
    visits = {v.flower: v for v in plan.planned}
    top = bot.info.travel_max[2]
    with journal.session(bot, started_visit=len(done)), \
            Tally(len(pending) if progress else 0, "visits") as tally:
        for flower in pending:
            t0 = bot.now()
            here = bot.position()
            bot.move_to([here[0], here[1], top])  # every visit starts from the top of Z
            entry = {"flower": flower}
            route = moves[flower]
            if look is not None:
                arrive = next(k for k, m in enumerate(route) if m.kind == "approach")
                rest = _fly_moves(bot, route[:arrive], plan.config.dwell_s)
                route, entry["look"] = look.visit(bot, visits[flower], route[arrive:])
            rest = _fly_moves(bot, route, plan.config.dwell_s)
            entry.update(t0=round(t0, 4), t1=round(bot.now(), 4),
                         rest=None if rest is None else [round(t, 4) for t in rest])
            flight["done"].append(entry)
            journal.save()
            tally.advance(1)
        here = bot.position()
        bot.move_to([here[0], here[1], top])
    return flight


def _fly_moves(bot: Bot, moves: list[Move], dwell_s: float) -> tuple[float, float] | None:
    """Fly `moves` in order; returns the bot-clock start and end of the rest on the flower
    (None: no rest among them)."""
    rest = None
    angles = bot.head()
    for move in moves:
        if move.kind == "dwell":
            start = bot.now()
            bot.dwell(dwell_s)
            rest = (start, bot.now())
            continue
        bot.move_to(move.pose.gantry)
        # The head turns at the top, clear of the plant, and at a path's waypoints once the
        # gantry is there, as the planner checked the path.
        wanted = head_angles(move.pose)
        if move.kind == "travel" or (move.kind in ("descend", "climb")
                                     and not np.allclose(wanted, angles)):
            bot.set_head(*wanted)
            angles = wanted
    return rest

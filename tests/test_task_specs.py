"""Every state of every task spec has a behaviour (issue 38): the runner names no state of its own, so a
state without one would end a task as internal_error; and every behaviour belongs to a state."""

from __future__ import annotations

import pytest

from palletpilot.executor.core.behaviour import Behaviour, Settings
from palletpilot.executor.core.tasks import TASK_SPECS, behaviours, build_machine
from palletpilot.executor.ports import Outcome

FINAL = {Outcome.SUCCEEDED.value, Outcome.FAILED.value}


@pytest.mark.parametrize("kind", sorted(TASK_SPECS))
def test_every_state_of_a_task_spec_has_a_behaviour(kind: str) -> None:
    spec = TASK_SPECS[kind]
    table = behaviours(kind, Settings())
    working = [s for s in spec.states if s not in FINAL]
    assert set(spec.states) >= FINAL
    assert sorted(table) == sorted(working), kind
    for state in working:
        assert issubclass(type(table[state]()), Behaviour), (kind, state)


@pytest.mark.parametrize("kind", sorted(TASK_SPECS))
def test_every_transition_joins_states_of_its_spec(kind: str) -> None:
    spec = TASK_SPECS[kind]
    for trigger, source, dest in spec.transitions:
        assert source == "*" or source in spec.states, (kind, trigger, source)
        assert dest in spec.states, (kind, trigger, dest)
    assert build_machine(kind).state == spec.states[0]

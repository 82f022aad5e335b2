"""Managed nodes from outside: their standard services, and the order a graph goes up and down in.

Any ROS 2 client drives a managed node through ``/<node>/get_state`` and
``/<node>/change_state`` (lifecycle_msgs); ``LifecycleClient`` calls them from a node that
some executor spins in another thread (the lifecycle manager's, or a tool's).

``transitions(goal, states, order)`` is the manager's plan, without ROS: the transitions that
bring every node from its state to ``goal``, nodes going up in ``order`` and coming down in
reverse, as nav2's lifecycle_manager does (the controller is active before the planner sends
it work, and the planner stops before the controller does).
"""

from __future__ import annotations

import threading

# Primary states, lowest first, and the transition that goes one step up or down from each.
LEVELS = ('unconfigured', 'inactive', 'active')
UP = {'unconfigured': 'configure', 'inactive': 'activate'}
DOWN = {'active': 'deactivate', 'inactive': 'cleanup'}
GOALS = (*LEVELS, 'finalized')


def transitions(goal: str, states: dict[str, str], order: list[str]) -> list[tuple[str, str]]:
    """(node, transition label) pairs that bring each node of ``order`` from ``states[node]`` to goal.

    Going up, every node takes its first step before any takes its second (all configured,
    then all activated), in ``order``; going down, in reverse order. 'finalized' is reached by
    each node's shutdown transition, from any primary state. ValueError on an unknown goal or
    state (a node in a transition state, or finalized, cannot be planned for).
    """
    if goal not in GOALS:
        raise ValueError(f'unknown goal state {goal!r}; one of {", ".join(GOALS)}')
    if goal == 'finalized':
        return [(node, 'shutdown') for node in reversed(order) if states[node] != 'finalized']
    unknown = {node: states[node] for node in order if states[node] not in LEVELS}
    if unknown:
        raise ValueError(f'cannot bring nodes in states {unknown} to {goal}')
    level = {node: LEVELS.index(states[node]) for node in order}
    target = LEVELS.index(goal)
    plan = []
    for step in range(len(LEVELS)):
        for node in order:
            if level[node] == step < target:
                plan.append((node, UP[LEVELS[step]]))
                level[node] += 1
    for step in reversed(range(len(LEVELS))):
        for node in reversed(order):
            if level[node] == step > target:
                plan.append((node, DOWN[LEVELS[step]]))
                level[node] -= 1
    return plan


class LifecycleClient:
    """The standard lifecycle services of one node, called from another node.

    Calls wait on their futures, so the calling node must be spun by an executor in another
    thread (a MultiThreadedExecutor serving this call's callback group, or a spin thread).
    """

    def __init__(self, node, target: str, callback_group=None):
        from lifecycle_msgs.srv import ChangeState, GetState      # here: the plan above needs no ROS
        self.target = target.lstrip('/')
        self._get = node.create_client(GetState, f'/{self.target}/get_state', callback_group=callback_group)
        self._change = node.create_client(ChangeState, f'/{self.target}/change_state',
                                          callback_group=callback_group)
        self._types = GetState, ChangeState

    def wait_for_services(self, timeout_s: float) -> bool:
        return self._get.wait_for_service(timeout_s) and self._change.wait_for_service(timeout_s)

    def get_state(self, timeout_s: float) -> str | None:
        """The node's state label, or None when it does not answer within timeout_s."""
        if not self._get.service_is_ready():
            return None
        response = _call(self._get, self._types[0].Request(), timeout_s)
        return None if response is None else response.current_state.label

    def change_state(self, transition: str, timeout_s: float) -> bool | None:
        """Trigger a transition by its label (configure, activate, ...): whether it succeeded,
        None when the node did not answer within timeout_s."""
        request = self._types[1].Request()
        request.transition.label = transition
        response = _call(self._change, request, timeout_s)
        return None if response is None else bool(response.success)

    def destroy(self, node) -> None:
        node.destroy_client(self._get)
        node.destroy_client(self._change)


def _call(client, request, timeout_s: float):
    done = threading.Event()
    future = client.call_async(request)
    future.add_done_callback(lambda _: done.set())
    if not done.wait(timeout_s):
        client.remove_pending_request(future)
        return None
    return future.result()

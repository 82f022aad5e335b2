"""lifecycle_manager: brings the managed HDP nodes up in order, keeps them there, takes them down.

As nav2's lifecycle_manager: ``node_names`` in the order they go up (controller_node before
planner_node: the controller is active before the planner sends it work); with ``autostart``
every node is configured, then every node activated, at start. Services (std_srvs/Trigger):

    ~/startup    configure and activate every node          ~/pause    deactivate, in reverse
    ~/resume     activate again                             ~/reset    deactivate and clean up
    ~/shutdown   every node through its shutdown transition ~/is_active success: all active

Once a second it asks each node its state. A node that appears, or comes back, unconfigured
while the graph should be active (it started late, hdp launch --respawn restarted it, someone
cleaned it up) is brought to active; one that stops answering is named on /hdp/status. A
transition that fails leaves the graph where it stood, says which node refused, and stops the
bring-up (the node's own status line says why); ~/startup tries again.
"""

from __future__ import annotations

import time

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.clock import Clock, ClockType
from std_srvs.srv import Trigger

from hdp_ros import ros
from hdp_ros.lifecycle import LifecycleClient, transitions

CHECK_S = 1.0


class LifecycleManager(ros.Node):
    PARAMETERS = {
        'node_names': (['controller_node', 'planner_node'], 'the managed nodes, in the order they go up'),
        'autostart': (True, 'bring every node to active at start'),
        'service_timeout_s': (60.0, 's to wait for a node to appear (its lifecycle services) at start-up'),
        'transition_timeout_s': (120.0, 's a transition may take (configure loads and warms up the models)'),
    }

    @staticmethod
    def check_parameters(p: dict) -> None:
        names = list(p['node_names'])
        if not names or len(set(names)) != len(names) or not all(n.strip() for n in names):
            raise ros.StartupError(f"parameter 'node_names' must name distinct nodes, got {names}")
        for name in ('service_timeout_s', 'transition_timeout_s'):
            if not p[name] > 0:
                raise ros.StartupError(f'parameter {name!r} must be > 0, got {p[name]}')

    def __init__(self):
        super().__init__('lifecycle_manager')
        p = self.declare_parameter_table()
        self.order = list(p['node_names'])
        self._service_timeout_s, self._transition_timeout_s = p['service_timeout_s'], p['transition_timeout_s']
        self.status = ros.Status(self)
        # Requests and the state check take turns (one group); service responses arrive meanwhile (another).
        self._turns = MutuallyExclusiveCallbackGroup()
        responses = ReentrantCallbackGroup()
        self.clients_by_node = {name: LifecycleClient(self, name, responses) for name in self.order}
        self.goal: str | None = None       # the state the graph should be in; None: nothing asked
        self._silent: set[str] = set()     # nodes that stopped answering, named once
        for service, goal in (('startup', 'active'), ('pause', 'inactive'), ('resume', 'active'),
                              ('reset', 'unconfigured'), ('shutdown', 'finalized')):
            self.create_service(Trigger, f'~/{service}', self._request(goal), callback_group=self._turns)
        self.create_service(Trigger, '~/is_active', self._is_active, callback_group=self._turns)
        self.create_timer(CHECK_S, self._check, clock=Clock(clock_type=ClockType.STEADY_TIME),
                          callback_group=self._turns)
        if p['autostart']:
            self._startup = self.create_timer(0.0, self._autostart, callback_group=self._turns)

    def _autostart(self) -> None:
        self.destroy_timer(self._startup)
        self.status.info(f'bringing up {", ".join(self.order)}')
        started = time.monotonic()
        end = started + self._service_timeout_s
        waiting = list(self.order)
        while waiting and time.monotonic() < end:
            waiting = [name for name in waiting if not self.clients_by_node[name].wait_for_services(0.5)]
        if waiting:
            self.status.error(f'no lifecycle services from {", ".join(waiting)} within {self._service_timeout_s:.0f} s '
                              '(are they running?): bringing up the others; they join when they appear')
        ok, message = self.bring_to('active')
        if ok:
            self.status.info(f'{message} in {time.monotonic() - started:.1f} s')

    def _request(self, goal: str):
        def serve(request, response):
            response.success, response.message = self.bring_to(goal)
            return response
        return serve

    def _is_active(self, request, response):
        states = self.states()
        response.success = all(state == 'active' for state in states.values())
        response.message = ', '.join(f'{name}: {state or "not answering"}' for name, state in states.items())
        return response

    def states(self) -> dict[str, str | None]:
        return {name: client.get_state(self._transition_timeout_s) for name, client in self.clients_by_node.items()}

    def bring_to(self, goal: str) -> tuple[bool, str]:
        """Take every node that answers to ``goal`` (a primary state or 'finalized'), in order;
        (success, what happened). Nodes that do not answer are named, and the goal stays: the
        state check brings them there when they appear."""
        self.goal = goal
        states = self.states()
        present = [name for name in self.order if states[name] is not None]
        try:
            plan = transitions(goal, {name: states[name] for name in present}, present)
        except ValueError as err:
            return self._failed(str(err))
        for node, transition in plan:
            started = time.monotonic()
            ok = self.clients_by_node[node].change_state(transition, self._transition_timeout_s)
            if not ok:
                why = 'no answer within the transition timeout' if ok is None else 'it refused (its status says why)'
                return self._failed(f'could not {transition} {node}: {why}; bring-up stopped')
            self.status.info(f'{transition} {node}: done in {time.monotonic() - started:.2f} s')
        silent = [name for name in self.order if name not in present]
        if silent:
            message = f'{", ".join(present) or "no node"} {goal}; not answering: {", ".join(silent)}'
            self.status.error(message)
            return False, message
        return True, f'{", ".join(self.order)} {goal}'

    def _failed(self, message: str) -> tuple[bool, str]:
        self.goal = None                   # nothing is retried until someone asks again
        self.status.error(message)
        return False, message

    def _check(self) -> None:
        """Name a node that stopped answering; bring one that came back below the goal up again."""
        if self.goal is None:
            return
        for name, client in self.clients_by_node.items():
            state = client.get_state(CHECK_S)
            if state is None:
                if name not in self._silent:
                    self._silent.add(name)
                    self.status.error(f'{name} does not answer its lifecycle services (did it exit?)')
                continue
            came_back = name in self._silent
            self._silent.discard(name)
            if self.goal == 'active' and state == 'unconfigured':
                self.status.info(f'{name} is {"back and " if came_back else ""}unconfigured: bringing it to active')
                self.bring_to('active')
                return


def main(args=None):
    ros.run(LifecycleManager, args, 'lifecycle_manager', threads=2)


if __name__ == '__main__':
    main()

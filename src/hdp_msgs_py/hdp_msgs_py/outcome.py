"""What the nodes report: a line on /hdp/status (StatusLine), and the planner's one structured
word on each instruction, on /hdp/outcome (Outcome).

planner_node publishes a std_msgs/String holding one JSON object per instruction when the
instruction ends (or is refused), so that a caller (`hdp demo`, a test, a user's script) learns
the result without parsing the human-readable lines on /hdp/status:

    {"instruction": "open the drawer", "result": "succeeded", "reason": "task succeeded after 3 segments",
     "segments": 3}
"""

from __future__ import annotations

import json
from typing import NamedTuple

RESULTS = (
    'succeeded',    # the task's success condition held
    'failed',       # a segment failed, a camera or the controller timed out, or the budget ran out
    'refused',      # never started: empty, too long, or nothing in it the agent was trained on
    'replaced',     # a newer instruction took over (queue_policy replace), running or waiting
    'ended',        # the segment budget ran out on a robot that reports no success
    'stopped',      # an operator stopped it (/hdp/stop), running or waiting
    'shutdown',     # the planner shut down while it ran or waited
)
MAX_INSTRUCTION_ECHO = 1024     # characters of a (refused) instruction repeated in its outcome


class StatusLine(NamedTuple):
    """A line for /hdp/status (and the node's log), as the node logic hands it to its node."""
    text: str
    error: bool = False


class Outcome(NamedTuple):
    instruction: str
    result: str                 # one of RESULTS
    reason: str
    segments: int               # NBPs sent for the instruction

    def to_json(self) -> str:
        if self.result not in RESULTS:
            raise ValueError(f'unknown outcome result {self.result!r}; one of {", ".join(RESULTS)}')
        return json.dumps({'instruction': self.instruction[:MAX_INSTRUCTION_ECHO], 'result': self.result,
                           'reason': self.reason, 'segments': int(self.segments)})

    @classmethod
    def from_json(cls, text: str) -> Outcome:
        """ValueError on anything but an outcome as to_json writes it."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as err:
            raise ValueError(f'an outcome is JSON: {err}') from None
        if not isinstance(data, dict) or set(data) != set(cls._fields):
            raise ValueError(f'an outcome is a JSON object with keys {", ".join(cls._fields)}')
        outcome = cls(**data)
        if (not all(isinstance(v, str) for v in outcome[:3]) or outcome.result not in RESULTS
                or not isinstance(outcome.segments, int) or outcome.segments < 0):
            raise ValueError(f'malformed outcome {text[:200]!r}')
        return outcome

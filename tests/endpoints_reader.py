"""List the DDS endpoints on the wire (topic and type names) the way any DDS tool sees them,
with no HDP code: plain cyclonedds and its builtin discovery topics. Prints JSON
{"publications": [[topic, type], ...], "subscriptions": [...]}.
"""

import json
import os
import time

from cyclonedds.builtin import BuiltinDataReader, BuiltinTopicDcpsPublication, BuiltinTopicDcpsSubscription

import cyclone_loopback

domain, participant = cyclone_loopback.participant(int(os.environ['ROS_DOMAIN_ID']))
readers = {'publications': BuiltinDataReader(participant, BuiltinTopicDcpsPublication),
           'subscriptions': BuiltinDataReader(participant, BuiltinTopicDcpsSubscription)}
seen = {kind: set() for kind in readers}
end = time.monotonic() + float(os.environ.get('LISTEN_S', '4'))
while time.monotonic() < end:
    time.sleep(0.2)
    for kind, reader in readers.items():
        for sample in reader.take(N=500):
            seen[kind].add((sample.topic_name, sample.type_name))
print(json.dumps({kind: sorted(pairs) for kind, pairs in seen.items()}))

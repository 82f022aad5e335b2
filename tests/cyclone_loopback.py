"""A plain Cyclone DDS participant on loopback, as the graph's Fast DDS profile has it
(no multicast, unicast discovery to localhost), for the tests' foreign peers."""

from cyclonedds.domain import Domain, DomainParticipant

CONFIG = ('<CycloneDDS><Domain Id="any"><General><Interfaces>'
          '<NetworkInterface address="127.0.0.1"/></Interfaces><AllowMulticast>false</AllowMulticast>'
          '</General><Discovery><ParticipantIndex>auto</ParticipantIndex>'
          '<MaxAutoParticipantIndex>64</MaxAutoParticipantIndex><Peers><Peer Address="localhost"/>'
          '</Peers></Discovery></Domain></CycloneDDS>')


def participant(domain_id: int) -> tuple[Domain, DomainParticipant]:
    """(domain, participant): keep the Domain alive, its configuration lives with it."""
    domain = Domain(domain_id, CONFIG)
    return domain, DomainParticipant(domain_id)

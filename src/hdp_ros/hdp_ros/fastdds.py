"""The Fast DDS profiles for a graph on more than one host, made from the templates in config/
for what the environment asks (hdp_ros.ros.use_project_profile chooses among them):

- network_profile: ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET or ROS_STATIC_PEERS; the localhost
  profile's shared memory and announcements, UDP on every interface, the static peers.
- tls_profile: HDP_DDS_TLS_DIR and HDP_DDS_DISCOVERY_SERVER (opt-in); every connection over TLS
  with certificates of the cell's CA, discovery through `hdp dds server`.

Fast DDS reads a profile from a file, so each is written, named by its content, into a
directory only this user can write (write_profile).
"""

import dataclasses
import hashlib
import os
import socket
import stat
import tempfile
import xml.etree.ElementTree as ElementTree
from pathlib import Path

CONFIG = Path(__file__).with_name('config')
NAMESPACE = 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'
# Fast DDS's discovery multicast group, which rmw_fastrtps_cpp also announces to under SUBNET.
MULTICAST_GROUP = '239.255.0.1'
# The port Fast DDS's own tools give a discovery server on TCP.
DISCOVERY_SERVER_PORT = 42100
# A host's credentials, as `hdp dds credentials` lays them out.
TLS_FILES = {'verify_file': 'ca.pem', 'cert_chain_file': 'cert.pem', 'private_key_file': 'key.pem'}
REQUIRE_PEER_CERTIFICATE = CONFIG / 'openssl_require_peer_certificate.cnf'

ElementTree.register_namespace('', NAMESPACE)     # written back as Fast DDS reads it: no ns0: prefixes


def _tag(path: str) -> str:
    return '/'.join(f'{{{NAMESPACE}}}{name}' for name in path.split('/'))


def _resolve(host: str, variable: str) -> str:
    """The IPv4 address of ``host``; a name Fast DDS cannot resolve would drop the whole profile."""
    try:
        return socket.gethostbyname(host)
    except (OSError, UnicodeError) as err:      # UnicodeError: not a name at all ('a..b')
        raise ValueError(f'{variable}: cannot resolve {host!r} ({err})') from None


def static_peers(environ) -> list[str]:
    """ROS_STATIC_PEERS (addresses or names, separated by ';', as rcl reads it) as IPv4 addresses."""
    return [_resolve(peer.strip(), 'ROS_STATIC_PEERS')
            for peer in environ.get('ROS_STATIC_PEERS', '').split(';') if peer.strip()]


def _udp_locator(address: str) -> ElementTree.Element:
    locator = ElementTree.Element(_tag('locator'))
    ElementTree.SubElement(ElementTree.SubElement(locator, _tag('udpv4')), _tag('address')).text = address
    return locator


def network_profile(peers: list[str], subnet: bool) -> str:
    """config/fastdds_network.xml with ``peers`` as initial peers; with ``subnet`` discovery also
    announces to and listens on the multicast group, else (static peers alone) no multicast, as
    rmw_fastrtps_cpp sets up each range."""
    root = ElementTree.parse(CONFIG / 'fastdds_network.xml').getroot()
    builtin = root.find(_tag('participant/rtps/builtin'))
    initial_peers = builtin.find(_tag('initialPeersList'))
    listed = {address.text for address in initial_peers.iter(_tag('address'))}
    for address in dict.fromkeys([*peers, *([MULTICAST_GROUP] if subnet else [])]):
        if address not in listed:
            initial_peers.append(_udp_locator(address))
    if not subnet:
        # An empty unicast locator: Fast DDS then makes no multicast listening locator.
        unicast = ElementTree.SubElement(builtin, _tag('metatrafficUnicastLocatorList'))
        ElementTree.SubElement(unicast, _tag('locator'))
    return ElementTree.tostring(root, encoding='unicode', xml_declaration=True)


@dataclasses.dataclass(frozen=True)
class TlsSettings:
    """What the TLS profile needs: this host's credentials and where the discovery server listens."""
    directory: Path
    server_address: str
    server_port: int


def tls_settings(environ) -> TlsSettings | None:
    """The TLS settings HDP_DDS_TLS_DIR and HDP_DDS_DISCOVERY_SERVER (host[:port]) ask for; None
    when neither is set. Half of them, or credentials that are not there, raise ValueError: Fast
    DDS would carry on without TLS."""
    directory, server = environ.get('HDP_DDS_TLS_DIR'), environ.get('HDP_DDS_DISCOVERY_SERVER')
    if not directory and not server:
        return None
    if not directory or not server:
        raise ValueError('the TLS profile needs both HDP_DDS_TLS_DIR (this host\'s credentials, from '
                         '`hdp dds credentials`) and HDP_DDS_DISCOVERY_SERVER (host[:port] of `hdp dds server`)')
    missing = [name for name in TLS_FILES.values() if not (Path(directory) / name).is_file()]
    if missing:
        raise ValueError(f'HDP_DDS_TLS_DIR={directory} lacks {", ".join(missing)} (`hdp dds credentials` makes them)')
    host, _, port = server.partition(':')
    if port and not port.isdigit():
        raise ValueError(f'HDP_DDS_DISCOVERY_SERVER={server}: the port must be a number')
    return TlsSettings(Path(directory).resolve(), _resolve(host, 'HDP_DDS_DISCOVERY_SERVER'),
                       int(port or DISCOVERY_SERVER_PORT))


def tls_profile(settings: TlsSettings, server: bool = False) -> str:
    """config/fastdds_tls.xml with this host's credentials and the discovery server's address; a
    client's by default, with ``server`` the discovery server's own (it listens on its port and
    announces the address the clients are given)."""
    root = ElementTree.parse(CONFIG / 'fastdds_tls.xml').getroot()
    tls = root.find(_tag('transport_descriptors/transport_descriptor/tls'))
    for element, name in TLS_FILES.items():
        tls.find(_tag(element)).text = str(settings.directory / name)
    rtps = root.find(_tag('participant/rtps'))
    discovery = rtps.find(_tag('builtin/discovery_config'))
    servers = discovery.find(_tag('discoveryServersList'))
    remote = servers.find(_tag('RemoteServer'))
    locators = remote.find(_tag('metatrafficUnicastLocatorList'))
    address = locators.find(_tag('locator/tcpv4'))
    address.find(_tag('address')).text = settings.server_address
    for port in ('physical_port', 'port'):
        address.find(_tag(port)).text = str(settings.server_port)
    if server:
        root.find(_tag('transport_descriptors/transport_descriptor/listening_ports/port')).text = \
            str(settings.server_port)
        discovery.find(_tag('discoveryProtocol')).text = 'SERVER'
        discovery.remove(servers)
        rtps.find(_tag('builtin')).append(locators)
        ElementTree.SubElement(rtps, _tag('prefix')).text = remote.get('prefix')
    return ElementTree.tostring(root, encoding='unicode', xml_declaration=True)


def runtime_dir(environ) -> Path:
    """Where this user's generated profiles go: $XDG_RUNTIME_DIR/hdp, else <tmp>/hdp-<uid>."""
    base = environ.get('XDG_RUNTIME_DIR')
    return Path(base) / 'hdp' if base else Path(tempfile.gettempdir()) / f'hdp-{os.getuid()}'


def _own_directory(path: Path) -> Path:
    """``path``, made if need be; refused unless it is a directory of this user's that no one
    else can write (a profile there decides which peers and certificates a process trusts)."""
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    info = path.lstat()
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & 0o022:
        raise PermissionError(f'{path} must be a directory of your own that others cannot write to')
    return path


def write_profile(environ, kind: str, text: str) -> Path:
    """``text`` in the runtime directory as fastdds_<kind>_<content hash>.xml: the same set-up
    gives the same file, so processes starting together agree on it."""
    digest = hashlib.sha256(text.encode()).hexdigest()[:16]
    path = _own_directory(runtime_dir(environ)) / f'fastdds_{kind}_{digest}.xml'
    if not path.is_file():
        partial = path.with_name(f'.{path.name}.{os.getpid()}')
        partial.write_text(text)
        os.replace(partial, path)       # atomic: a process starting beside this one reads all or none
    return path


def is_tls_profile(path: str | None, environ) -> bool:
    """Whether ``path`` is a TLS profile written by write_profile (a client's or the server's)."""
    return bool(path) and Path(path).parent == runtime_dir(environ) and Path(path).name.startswith('fastdds_tls')

"""Stand-ins for the ROS 2 launch API (launch, launch_ros, ament_index_python), which the package
registry does not have: a launch file's generate_launch_description() runs against them and
the test reads what it would start, with which arguments."""

import sys
import types
from pathlib import Path


class Action:
    """A launch action or launch_ros Node: keeps what it was made with."""
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


class LaunchConfiguration:
    def __init__(self, name):
        self.name = name

    def perform(self, context):
        return context[self.name]


def install(monkeypatch, shares: dict) -> None:
    """Put the stand-ins in sys.modules; get_package_share_directory(p) returns shares[p]."""
    modules = {
        'launch': types.SimpleNamespace(LaunchDescription=lambda actions: list(actions)),
        'launch.actions': types.SimpleNamespace(DeclareLaunchArgument=Action, OpaqueFunction=Action,
                                                IncludeLaunchDescription=Action),
        'launch.launch_description_sources': types.SimpleNamespace(PythonLaunchDescriptionSource=Action),
        'launch.substitutions': types.SimpleNamespace(LaunchConfiguration=LaunchConfiguration),
        'launch_ros.actions': types.SimpleNamespace(Node=Action),
        'ament_index_python.packages': types.SimpleNamespace(get_package_share_directory=lambda p: str(shares[p])),
    }
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)


def run(path: Path, given: dict) -> tuple[list, dict]:
    """(what the launch file's OpaqueFunction returns for the arguments ``given``, the declared
    arguments' defaults). install() first."""
    namespace = {}
    exec(compile(path.read_text(), str(path), 'exec'), namespace)
    actions = namespace['generate_launch_description']()
    declared = {a.args[0]: a.kwargs['default_value'] for a in actions if 'default_value' in a.kwargs}
    (function,) = [a for a in actions if 'function' in a.kwargs]
    return function.kwargs['function']({**declared, **given}), declared

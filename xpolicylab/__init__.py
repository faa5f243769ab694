"""XPolicyLab: integrate a robot policy once, evaluate it anywhere.

The policy-side standard of RoboDojo: the ``Model`` interface, a WebSocket + MessagePack server and client
(native XPolicyLab dialect and openpi dialect), an offline checker, reference policies and a package template.
It depends only on numpy, msgpack and websockets, so a policy's own environment can install it alone; it never
imports the simulator.
"""

from xpolicylab.errors import ErrorCode, ProtocolError
from xpolicylab.model import Model, PolicyMetadata

__all__ = ["ErrorCode", "Model", "PolicyMetadata", "ProtocolError"]
__version__ = "0.1.0"

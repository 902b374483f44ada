"""Evaluation protocols, a registry kind: each names an env condition plus a controller setting.

The registry imports every module here on the kind's first lookup; ``paper.py``
registers the paper's Table 1 conditions. A user adds a protocol the way they
add a detector: ``@ddp.register("protocol", "ood_push", config=NoOptions)`` on a
function returning an :class:`~ddp.protocols.base.EvalProtocol`.
"""

"""What any settings dataclass says of its fields, and the bounds every setting shares.

:func:`dataclass_field_types` and :func:`dataclass_field_docs` read a dataclass's fields (a run
config's sections, a plug-in's settings, the sweep's :class:`~imssr.sweep.grid.SweepConfig`):
their types, which the overrides convert to, and their docstrings, which the CLI's help shows.
"""
from __future__ import annotations

import dataclasses
import functools
import sys
import typing
from typing import Any

from docstring_parser import parse_from_object

MAX_SEED = 2**31 - 1
"""Largest run seed: numpy's and dm_control's seeds are 32-bit, and evaluation envs use the run
seed + 10,000 and + 20,000, so seeds stay below 2**31 (the sweep's seeds are checked the same)."""
MAX_INT = 2**31 - 1
"""Largest value of any integer setting that has no tighter bound: counts, sizes and intervals
beyond it are typing slips (``1e15``) and would end in an allocation or overflow traceback."""
MAX_IMAGE_SIZE = 480
"""Largest rendered image side: MuJoCo renders offscreen into the models' framebuffer, 640x480 in
every DeepMind Control model (their shared visual settings)."""
MAX_ADDRESSABLE_BYTES = sys.maxsize
"""Largest array a process can address (numpy's limit): bounds the replay buffer's frames."""
MAX_SHADOW_SIZE = 4096
"""Largest MuJoCo shadow map side (``env.shadow_size``): MuJoCo's own default (dm_control's
suite renders 2048, the presets 512).  A frame is at most :data:`MAX_IMAGE_SIZE` px, so a larger
map sharpens no shadow in it, while its cost grows with its area: on Mesa's llvmpipe a 64-px
frame took 36 ms at 4096, 0.37 s at 16384 (with 1 GiB of depth texture per env and 3 s to make
each), so that a SIGTERM waited seconds for the agent step, or the env's making, to end.  (The
hard limit, 16384, is the largest OpenGL texture side every OpenGL 4.1 renderer takes.)"""
MAX_TORCH_THREADS = 1024
"""Most torch intra-op threads (``train.torch_threads``): more than any CPU has hardware threads
to run them on, far below what OpenMP can start (a thread per pid: Linux's default ``pid_max``
is 32768, and libgomp aborts the process when a thread cannot be made).  A fixed number, not the
machine's core count, as a config is checked on the machine that writes it (a sweep's) too."""
MIN_CROP_SIZE = 3
"""Smallest crop (``agent.crop_size``): the encoder's first convolution is 3x3, without padding."""
ADAM_BETA_RULE = "in [0, 1) (torch's Adam)"
"""What torch's Adam accepts of a beta: 0 <= beta < 1."""
SEED_RULE = f"an integer in [0, {MAX_SEED}] (numpy and dm_control take 32-bit seeds, and evaluation adds up to 20000)"


@functools.cache
def dataclass_field_types(cls: type) -> dict[str, Any]:
    """The fields of the dataclass ``cls`` -> their declared types, resolved (``int``,
    ``Optional[int]``, ``list[str]``), in the order of the fields."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


@functools.cache
def dataclass_field_docs(cls: type) -> dict[str, str]:
    """The fields of the dataclass ``cls`` -> their docstrings (whitespace collapsed), read once
    from the source of ``cls`` and of the dataclasses it inherits fields from (a section composed
    of plug-ins' settings has no source of its own); empty when installed without sources."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            docs.update({doc.arg_name: " ".join(doc.description.split())
                         for doc in parse_from_object(klass).params
                         if doc.args[0] == "attribute" and doc.description})
    return {name: docs[name] for name in dataclass_field_types(cls) if name in docs}


def type_phrase(kind: type) -> str:
    """How an error names a field's type: "an integer", "a number", "true or false", "a string"."""
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}.get(kind, f"a {kind.__name__}")

"""The ``parproj`` sub-commands, one module each: ``add_parser(sub)`` and ``run(args)``."""

from __future__ import annotations

from . import (
    batch,
    demo,
    dsm,
    evaluate,
    fuse,
    import_images,
    paper,
    process,
    replay,
    segments,
    simulate,
    ventoux_eval,
)

#: In the order ``parproj --help`` lists them.
COMMANDS = (
    paper,
    simulate,
    process,
    replay,
    evaluate,
    demo,
    import_images,
    ventoux_eval,
    segments,
    batch,
    dsm,
    fuse,
)

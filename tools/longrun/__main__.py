"""``python -m tools.longrun [--minutes M] [--repetitions N] [-o DIR] ...``.

See :mod:`tools.longrun`.
"""

from tools.longrun.run import main

raise SystemExit(main())

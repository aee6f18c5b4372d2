"""``python -m tools.bench [--quick] [--json] ...``: see :mod:`tools.bench`."""

from tools.bench.run import main

raise SystemExit(main())

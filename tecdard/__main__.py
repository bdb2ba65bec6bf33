"""`python -m tecdard` is the `tecdard` command."""
from tecdard.cli import main

raise SystemExit(main())

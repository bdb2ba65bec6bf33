"""`python -m tecdard` is the `tecdard` command."""
from tecdard.cli.main import main

raise SystemExit(main())

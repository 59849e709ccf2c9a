"""`python -m gvae_core` is the `gvae` command line."""

from .cli import main

raise SystemExit(main())

"""The checkout's own tooling: the linters run on the installed package names."""

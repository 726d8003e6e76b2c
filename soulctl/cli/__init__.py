"""The soulctl command line: one module per command group."""

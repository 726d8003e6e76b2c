"""The soulctl command line: one module per command group."""

import logging

# Before any command module imports matplotlib: its complaints about a cache folder it cannot
# make are not the user's business and would break the one-line refusal of the contract.
logging.getLogger("matplotlib").setLevel(logging.ERROR)

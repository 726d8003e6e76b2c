"""What soulctl computes from a recorded loop: the loop a record ran (``recorded``) and the
Modal Gain Machine on it (``mgm``).  Above ``loop`` and ``run_config``: a record's run
description is read back into a ``run_config.RunConfig``."""

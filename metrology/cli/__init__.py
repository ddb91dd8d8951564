"""The ``doe`` subcommands of the metrology package: compare, calibrate, diagnose, demo."""

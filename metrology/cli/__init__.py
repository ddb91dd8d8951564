"""The ``doe`` subcommands of the metrology package: compare, calibrate, diagnose, demo."""

__all__: list[str] = []

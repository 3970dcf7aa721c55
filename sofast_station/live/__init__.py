"""What the running station shares with its monitor and its operators, through files under ``data_dir``:
the live status (``status.py``, ``live/status.json``), each facet's small pictures (``pictures.py``,
``live/facets/``), the operators' commands to the loop (``operator_commands.py``, ``commands/``) and the
log files (``logs.py``, ``logs/``).

The station's loop writes and takes them; the line's page and OPC UA server (``web/``), in a process of
their own, read them and post commands. Neither imports the other's code for it: this package is below
both.
"""

"""``python -m service serve [--demo]``: the service's command (``service/cli.py``)."""

from service.cli import main

if __name__ == "__main__":
    main()

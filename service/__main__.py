"""``python -m service``: run the service with settings from SWARMLOC_* environment variables."""

from service.server import run
from service.settings import Settings

if __name__ == "__main__":
    run(Settings())

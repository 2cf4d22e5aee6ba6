"""Allow ``python -m amigo``."""

from amigo.cli import console

if __name__ == "__main__":
    console()

"""Allow ``python -m amigo``."""

from amigo.cli import main

if __name__ == "__main__":
    main()

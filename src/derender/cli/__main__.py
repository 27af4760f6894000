"""``python -m derender.cli``: the ``derender`` command."""

from derender.cli import main

if __name__ == "__main__":   # importing the module (e.g. Sphinx's autosummary) runs nothing
    main()

"""``python -m derender.cli``: the ``derender`` command."""

from derender.cli import console_main

if __name__ == "__main__":   # importing the module (e.g. Sphinx's autosummary) runs nothing
    console_main()

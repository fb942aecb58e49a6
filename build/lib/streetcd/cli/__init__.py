"""Thin command line over the library. Progress bars live here, never in the library.

Nothing here imports click: ``streetcd query`` runs without it (:mod:`streetcd.cli.query`).
The options the click commands share are in :mod:`streetcd.cli.options`.
"""

INDEX_HELP = "The change index (SQLite) a run wrote."

"""The review page: a night's change objects as a static site (``streetcd report``) or live,
with review decisions recorded into the index (``streetcd serve``).

Layer 7, beside ``cli/``: it reads the index (``store/``), the run's inputs (``io/``, the
tile store) and renders thumbnails; nothing below imports it. Modules:

``changes``  what the page shows, read from the index (:func:`~streetcd.report.changes.load_changes`
             is the one adapter to the change objects of ``store.objects``)
``render``   thumbnails: the view's image, the old cloud splatted from the same pose
``site``     the static site: ``index.html``, its assets, ``data.js`` and the thumbnails
``server``   the live page: a small threaded HTTP server over the same site
``export``   ``streetcd query`` for people and GIS: sorting, a box in any CRS, CSV, GeoPackage
"""

"""services.console: the commissioning console, a web page served by ``autotune console``.

A client of the bus like the CLI (nothing of it lives in the services): ``bridge`` joins
Zenoh and keeps the loops' trends, the services present, the runs' progress and results;
``actions`` runs tune, cancel, apply, reject and revert through the CLI's own request and
lease paths; ``server`` serves the page (``static/``, shipped as package data: no CDN) over
HTTP and pushes live data to it over a websocket.
"""

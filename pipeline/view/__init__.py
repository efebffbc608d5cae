"""The live web page (``tcspc view``): the running daemon and the sensor as a person looks at
them. It reads the daemon's status PUB (``status.json`` when nobody publishes) and the
datasets the sink wrote; it never sits in the stream.

- ``status``: status.json and the status PUB into health rows, rates and the daemon's state;
- ``datasets``: the runs under OUT, one measurement's histograms and ranges, the accounting
  identity;
- ``sensor``: the array's maps, a histogram's marks (reset peak, return), the calibration
  in use and the drift of the online LSB estimate;
- ``model``: one refresher per server that keeps the latest of all of the above;
- ``page`` and ``server``: the Bokeh document of a browser session, and the server.

The first four are plain functions and classes over files and dicts (tested without a
browser); only ``page`` and ``server`` import Bokeh.
"""

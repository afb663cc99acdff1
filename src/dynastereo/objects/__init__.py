"""Dynamic objects: what moves, where it is and how fast it goes.

The data flow of a frame is io -> masking -> objects -> slam -> eval.  The masker gives
each detected object its outline and disparity in both images; this package then

* :mod:`.motion` -- judges each tracked object moving or static from stereo scene flow
  against the camera's motion (``ObjectMotion``: ``measure`` on the masking thread,
  ``select`` the masks SLAM gets, ``update`` after tracking, which returns the map edits of
  objects that turned moving; the frame processor applies them through the SLAM's public
  API, ``System.forget_region``);
* :mod:`.disparity` -- matches each object's outline again with the objects' own block
  (``ObjectStereo``), for better positions than the masks' disparity;
* :mod:`.world` -- places each object in the world and follows it with a filter
  (``WorldObjects``: positions, extents, headings, velocities and speeds), and writes
  ``objects_tracks.csv`` (``TrackWriter``).

``slam`` imports nothing from here: the SLAM sees masks and map edits, never objects.
"""

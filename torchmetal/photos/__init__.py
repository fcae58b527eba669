"""Phone photos → capture (docs/design.md §2.6): a printable ChArUco board with a window for the sample,
detection, self-calibration, poses, rectification, exposure and white balance (EXIF, white band).

==========================  ================================================================
module                      what
==========================  ================================================================
:mod:`.board`               the board's geometry (board.json) and its exact raster (board.png)
:mod:`.exif`                exposure and camera from EXIF (Pillow)
:mod:`.detect`              one photo: decode, ChArUco corners, blur, the window's crop
:mod:`.calibrate`           intrinsics from the photo set, poses, camera and flash positions
:mod:`.rectify`             the window resampled onto the capture grid, area-correct
:mod:`.white`               the white reference from the paper band's unclipped part
:mod:`.capture`             the whole pipeline and the capture directory it writes
:mod:`.report`              the contact sheet
:mod:`.simulate`            generated phone photos with their truth (tests, notebook, bench)
:mod:`.cli`                 the ``board`` and ``capture`` verbs
==========================  ================================================================

Importing this package is free (nothing heavy): import the modules you use.
"""

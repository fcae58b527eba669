"""Relight a material in the browser.

- ``torchmetal view MATERIAL`` (:mod:`torchmetal.viewer.server`): a local page whose frames the
  Python server renders with onnxruntime from the material's ONNX file.
- ``torchmetal export MATERIAL --format web -o SITE/`` (:mod:`torchmetal.formats.web`): the same
  page as a static folder that renders in the browser with onnxruntime-web.

Both share the page in ``static/`` and the config/graphs/photos of :mod:`torchmetal.viewer.site`.
"""

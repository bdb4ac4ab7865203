"""`dofjax view`: a local web app to refocus an RGB-D image live, compare with the lens-sampling
reference and fit the camera to a photograph. A thin app over the library; see docs/viewer.md."""

from ._app import create_app as create_app
from ._engine import Bokeh as Bokeh, Engine as Engine
from ._serve import bind as bind, serve as serve
from ._source import Source as Source, load_source as load_source

"""Array shape aliases shared by the public API."""

from jaxtyping import Array, Float, Int

Image = Float[Array, "h w 3"]
Depth = Float[Array, "h w"]
Scalar = Float[Array, ""]
Vec3 = Float[Array, "3"]
Points = Float[Array, "n 3"]
Indices = Int[Array, " n"]
LayerImages = Float[Array, "k h w 3"]
LayerMaps = Float[Array, "k h w"]

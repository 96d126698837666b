"""Error types the engine raises on bad input.

Each failure a user can cause has its own type so the CLI can print one clear line and the
service can map it to a specific 4xx without parsing messages.
"""


class HKTexError(Exception):
    """Base of every error the engine raises deliberately."""


class MeshError(HKTexError):
    """The mesh cannot be used; subclasses say why."""


class UnreadableMeshError(MeshError):
    """The file is not a mesh we can parse (garbage, truncated, unknown format)."""


class EmptyMeshError(MeshError):
    """The file parsed but holds no triangles."""


class NonFiniteError(MeshError):
    """Vertex coordinates contain NaN or infinity."""


class DegenerateFacesError(MeshError):
    """Faces with (near-)zero area or repeated vertex indices."""


class NonManifoldError(MeshError):
    """An edge shared by more than two faces, or a vertex whose faces are not one fan."""


class DisconnectedMeshError(MeshError):
    """More than one connected component."""


class TooManyVerticesError(MeshError):
    """More vertices than the configured limit."""


class TextureError(HKTexError):
    """A texture is missing, unreadable, or does not fit the mesh's UVs."""


class SpectraError(HKTexError):
    """A spectra directory is missing, corrupt, or does not match the mesh/config asked for."""


class KernelSetError(HKTexError):
    """A kernel-set file is truncated, foreign, inconsistent, or fitted on other spectra."""


class ViewsError(HKTexError):
    """A multi-view dataset is malformed (missing cameras, size mismatch, empty masks)."""


class QueryError(HKTexError):
    """A query is malformed: out-of-range face ids, bad barycentrics, NaNs, wrong shapes."""


class Cancelled(HKTexError):
    """A long task stopped because its owner asked it to (cooperative cancellation)."""


class RenderError(HKTexError):
    """Rendering cannot run: no Mitsuba AD variant loads, or the scene cannot be built."""

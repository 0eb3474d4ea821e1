"""The dataset file's identity, shared by the rod (:mod:`dlocli.data`) and marker
(:mod:`dlocli.markers.dataset`) datasets."""

FORMAT = "dlocli-dataset"
FORMAT_VERSION = 2  # 2: the ``form`` attribute ("rod", or "markers")
DATASET_FILE = "dataset.h5"

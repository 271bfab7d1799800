"""The segmentation-model lab: everything that exists to produce or study RoadSegNet, the model the
product ships as common/models/roadseg.onnx. Not part of the installed product (run it from a
checkout with `pip install -e '.[train]'`; `python -m training train-seg --help`)."""

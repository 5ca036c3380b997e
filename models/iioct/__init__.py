"""The simulated iiOCT sensor (public module): A-scan synthesis and distance extraction.

    engine = OctEngine()                                  # IOL Master 700-like defaults
    a = synthesize_ascan(10.0, 0.1, rng, engine=engine)   # retina 10 mm ahead, 0.1 rad
    m = DistanceExtractor(engine)(a)                      # Measurement(distance_mm, valid, ...)

Synthesis lives in models.iioct.ascan, extraction in models.iioct.segmentation, the
extractor's error model (the closed loop's fast "distance" mode) in models.iioct.error_model.
"""
from models.iioct.ascan import VITREOUS_GROUP_INDEX, Floater, OctEngine, synthesize_ascan
from models.iioct.segmentation import REASONS, DistanceExtractor, Measurement, extract_distance

__all__ = ["REASONS", "VITREOUS_GROUP_INDEX", "DistanceExtractor", "Floater", "Measurement", "OctEngine",
           "extract_distance", "synthesize_ascan"]

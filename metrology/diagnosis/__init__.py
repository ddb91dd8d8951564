"""Diagnosis: the registry of physical effects and artefacts, the model-selection engine
that names the effect a measurement shows and the model lacks, and the hidden-effect
generator used by the demo.
"""

"""Scoring against the truth: truth readers (plant.json, SageMaker, the label file), matching
and a plant's score, the statistics every interval comes from, two runs compared flower by
flower, external methods scored alike, and a real labelled plant's folder."""

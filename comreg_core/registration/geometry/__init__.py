"""The registration's geometry: the CT surface (exact distances, samples, closest points), one
batched point-to-plane ICP, its compiled kernels, the metrics (RTE, RRE, CD, HD95) and the US
cloud's limits. Imports nothing else of ``registration``.
"""

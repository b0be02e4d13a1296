"""The paper's reference controllers (laws I-III), their gain rule and the nominal dynamics they use."""

//! weights-tool library: checkpoint reading, synthetic weights, conversion.

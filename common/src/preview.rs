//! PNG previews of height maps (in progress).

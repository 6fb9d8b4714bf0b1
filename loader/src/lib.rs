//! strata-loader: selects the octree cut per frame and streams bricks from storage to the GPU cache.
//! (Filled in by the loader issue; the crate exists so its boundaries hold from day one.)

//! The editing tools. Each takes the layer (and, where it reads the primary, an
//! [`Intensity`](crate::intensity::Intensity)) and makes one [`Edit`](crate::Edit): one undo
//! step, one journal record.

pub mod brush;

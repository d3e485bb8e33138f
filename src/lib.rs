pub mod geom;
pub mod io;
pub mod mem;

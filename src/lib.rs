pub mod geom;
pub mod io;

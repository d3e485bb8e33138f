//! The bound on member lists held at once: a batch of [`super::Engine::members`] on the
//! CPU engine (the edge fit's decision rule, the straightness check) and each batch of
//! `--split-gaps`' sorted axial positions list at most [`MAX_LISTED_MEMBERS`] members
//! in all. Past it the step ends with [`EngineError::Limit`] (exit code 1) and a message
//! that names the bound and how to raise it, before the lists grow further.

use super::EngineError;

/// Most members a batch of member lists holds in all: 2^25 (a listed member takes 40
/// bytes, so 1.3 GB; a sorted axial position 8 bytes, so 268 MB).
/// `LINEGS_MAX_LISTED_MEMBERS` sets another value.
pub const MAX_LISTED_MEMBERS: usize = 1 << 25;

/// Bytes a listed member takes ([`super::Member`]), for the message.
const MEMBER_BYTES: usize = std::mem::size_of::<super::Member>();

/// The process's `LINEGS_MAX_LISTED_MEMBERS` as the command line read it (the library
/// reads no environment): `None` keeps the default bound.
static SETTING: std::sync::RwLock<Option<String>> = std::sync::RwLock::new(None);

/// Sets the bound on the members a batch of lists holds (the text of
/// `LINEGS_MAX_LISTED_MEMBERS`, checked when a batch starts; `None`: the default).
pub fn set_max_listed_members(v: Option<String>) {
    if let Ok(mut s) = SETTING.write() {
        *s = v;
    }
}

/// The bound in force: [`MAX_LISTED_MEMBERS`] or the value set.
#[derive(Clone, Copy, Debug)]
pub struct ListBound {
    pub limit: usize,
    from_env: bool,
}

impl ListBound {
    /// A bound of `limit` members (tests).
    pub fn of(limit: usize) -> Self {
        ListBound {
            limit,
            from_env: false,
        }
    }

    /// The bound in force; an unreadable `LINEGS_MAX_LISTED_MEMBERS` is
    /// [`EngineError::Limit`] too, naming it.
    pub fn new() -> Result<Self, EngineError> {
        let setting = SETTING.read().map(|s| s.clone()).unwrap_or(None);
        match setting {
            None => Ok(ListBound {
                limit: MAX_LISTED_MEMBERS,
                from_env: false,
            }),
            Some(v) => match v.trim().parse::<usize>() {
                Ok(n) if n > 0 => Ok(ListBound {
                    limit: n,
                    from_env: true,
                }),
                _ => Err(EngineError::Limit(format!(
                    "LINEGS_MAX_LISTED_MEMBERS={v:?} is not a positive whole number"
                ))),
            },
        }
    }

    /// The error of a batch (`what` lists them) that needs more than the bound.
    pub fn exceeded(&self, what: &str) -> EngineError {
        EngineError::Limit(format!(
            "{what} needs more than {} listed members in one batch, and a batch holds at \
             most {}{} ({MEMBER_BYTES} bytes each, so at most {:.1} MB): the segments cross \
             too many Gaussians at this radius; try a smaller --radius, or raise the bound \
             with LINEGS_MAX_LISTED_MEMBERS=N where the machine has the memory",
            self.limit,
            self.limit,
            if self.from_env {
                " (LINEGS_MAX_LISTED_MEMBERS)"
            } else {
                ""
            },
            (self.limit as f64 * MEMBER_BYTES as f64) / 1e6,
        ))
    }
}

//! Error reporting shared by every layer.

/// The error and its causes, `: `-separated, each cause once (a cause whose text the message
/// already contains, as `#[error(transparent)]` and `{source}` messages do, is not repeated).
pub fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut src = e.source();
    while let Some(c) = src {
        let t = c.to_string();
        if !s.contains(&t) {
            s.push_str(": ");
            s.push_str(&t);
        }
        src = c.source();
    }
    s
}

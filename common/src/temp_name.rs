//! The hidden name an output is written under before it is renamed into place.

use std::path::{Path, PathBuf};

/// Longest part of the output's name kept in its temporary's name: with the dot, `.tmp`,
/// a process id and a counter the temporary stays within the 255 bytes a file name may
/// have wherever the output's own name does.
const KEPT: usize = 200;

/// `.NAME.tmpPID` beside `path` (hidden, same folder, so the rename stays on one file
/// system), for process `pid`; see [`temp_sibling_numbered`] for long names.
pub fn temp_sibling(path: &Path, pid: u32) -> Option<PathBuf> {
    static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    temp_sibling_numbered(path, pid, n)
}

/// [`temp_sibling`] with the counter `n` given: a name longer than 200 bytes is cut to its
/// first 200 (at a character boundary) and `-N` appended, so that two long names with one
/// prefix get two temporaries. `None` for a path without a file name.
pub fn temp_sibling_numbered(path: &Path, pid: u32, n: u64) -> Option<PathBuf> {
    let name = path.file_name()?.to_string_lossy();
    if name.len() <= KEPT {
        return Some(path.with_file_name(format!(".{name}.tmp{pid}")));
    }
    let mut end = KEPT;
    while !name.is_char_boundary(end) {
        end -= 1;
    }
    Some(path.with_file_name(format!(".{}.tmp{pid}-{n}", &name[..end])))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_names_get_temporaries_within_the_limit_and_distinct() {
        let short = temp_sibling_numbered(Path::new("out/frame.png"), 42, 7).unwrap();
        assert_eq!(short, PathBuf::from("out/.frame.png.tmp42"));
        let a = format!("{}_c1r2.png", "é".repeat(120));
        let b = format!("{}_c1r3.png", "é".repeat(120));
        assert!(a.len() <= 255);
        let ta = temp_sibling_numbered(Path::new(&a), u32::MAX, u64::MAX).unwrap();
        let tb = temp_sibling_numbered(Path::new(&b), u32::MAX, u64::MAX - 1).unwrap();
        let na = ta.file_name().unwrap().len();
        assert!(na <= 255, "{na} bytes");
        assert!(ta.to_str().unwrap().starts_with(".éé"));
        assert_ne!(ta, tb);
        assert_eq!(temp_sibling(Path::new("/"), 1), None);
    }
}

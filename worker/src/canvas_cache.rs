//! The coordinator's canvases a worker keeps mapped between frames.
//!
//! A canvas is a shared-memory image the coordinator owns; a worker that blends its final
//! piece into it maps it once and keeps the mapping for the next frames, as the coordinator
//! rotates a few live canvases. A mapping also keeps the segment alive, so the cache lets go
//! of a canvas the coordinator stopped asking for (a failed attempt's, one of another size)
//! after [`STALE`] frames, and holds at most [`KEEP`].

use std::collections::HashMap;

/// Canvases kept mapped (the coordinator rotates two while callers hold images).
pub const KEEP: usize = 4;

/// Frames after which a canvas not asked for is let go: the coordinator uses each of its
/// live canvases every other frame or so, and drops a failed attempt's and those of another
/// size, which a mapping here would keep from being freed (a live one let go is only mapped
/// again).
pub const STALE: u64 = 4;

/// What the cache needs to know of a canvas.
pub trait Canvas {
    /// The segment's name (the coordinator's key for it).
    fn name(&self) -> &str;
    /// Width and height in pixels.
    fn size(&self) -> (u32, u32);
}

impl Canvas for strata_net::canvas::CanvasWriter {
    fn name(&self) -> &str {
        strata_net::canvas::CanvasWriter::name(self)
    }
    fn size(&self) -> (u32, u32) {
        strata_net::canvas::CanvasWriter::size(self)
    }
}

/// The mapped canvases, most recently returned last.
pub struct CanvasCache<W> {
    held: Vec<W>,
    /// The last frame that asked for each canvas (by name), for the held ones and the one
    /// asked for last.
    used: HashMap<String, u64>,
}

impl<W> Default for CanvasCache<W> {
    fn default() -> Self {
        CanvasCache {
            held: Vec::new(),
            used: HashMap::new(),
        }
    }
}

impl<W: Canvas> CanvasCache<W> {
    /// Frame `frame` asks for canvas `name` of `size`: lets go of the canvases of another
    /// size and those not asked for in the last [`STALE`] frames, then hands out the held
    /// mapping of `name` if there is one. Otherwise the caller maps it, after
    /// [`make_room`](Self::make_room).
    pub fn take(&mut self, name: &str, size: (u32, u32), frame: u64) -> Option<W> {
        let used = &mut self.used;
        used.insert(name.to_string(), frame);
        self.held.retain(|w| {
            let recent = used
                .get(w.name())
                .is_some_and(|&f| f.saturating_add(STALE) >= frame);
            w.size() == size && recent
        });
        let live: std::collections::HashSet<&str> = self.held.iter().map(|w| w.name()).collect();
        used.retain(|n, _| n == name || live.contains(n.as_str()));
        let i = self
            .held
            .iter()
            .position(|w| w.name() == name && w.size() == size)?;
        Some(self.held.remove(i))
    }

    /// Lets go of the oldest canvases until a new one fits under [`KEEP`].
    pub fn make_room(&mut self) {
        while self.held.len() >= KEEP {
            self.held.remove(0);
        }
    }

    /// Returns a canvas after its frame.
    pub fn put(&mut self, w: W) {
        self.held.push(w);
    }

    /// The canvases held, oldest first.
    pub fn held(&self) -> impl Iterator<Item = &W> {
        self.held.iter()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A canvas by name and size (the cache reads nothing else).
    struct Named(String, (u32, u32));

    impl Canvas for Named {
        fn name(&self) -> &str {
            &self.0
        }
        fn size(&self) -> (u32, u32) {
            self.1
        }
    }

    /// One frame asking for `name`: takes it (mapping it anew where not held) and returns it.
    /// Says whether it was held.
    fn frame(c: &mut CanvasCache<Named>, name: &str, size: (u32, u32), f: u64) -> bool {
        let held = c.take(name, size, f);
        let was = held.is_some();
        let w = held.unwrap_or_else(|| {
            c.make_room();
            Named(name.into(), size)
        });
        c.put(w);
        was
    }

    fn names(c: &CanvasCache<Named>) -> Vec<&str> {
        let mut v: Vec<&str> = c.held().map(|w| w.name()).collect();
        v.sort();
        v
    }

    #[test]
    fn canvases_in_rotation_stay_mapped() {
        let mut c = CanvasCache::default();
        for f in 0..20 {
            let name = if f % 2 == 0 { "a" } else { "b" };
            assert_eq!(frame(&mut c, name, (8, 8), f), f >= 2, "frame {f}");
        }
        assert_eq!(names(&c), ["a", "b"]);
    }

    /// A failed attempt's canvas, which the coordinator never asks for again, is let go
    /// after STALE frames (it had stayed mapped for the run, keeping its memory).
    #[test]
    fn a_canvas_not_asked_for_is_let_go_after_stale_frames() {
        let mut c = CanvasCache::default();
        frame(&mut c, "failed", (8, 8), 0);
        for f in 1..=STALE {
            frame(&mut c, "a", (8, 8), f);
            assert!(names(&c).contains(&"failed"), "frame {f}: {:?}", names(&c));
        }
        frame(&mut c, "a", (8, 8), STALE + 1);
        assert_eq!(names(&c), ["a"]);
    }

    #[test]
    fn canvases_of_another_size_are_let_go_at_once() {
        let mut c = CanvasCache::default();
        frame(&mut c, "a", (8, 8), 0);
        frame(&mut c, "b", (8, 8), 1);
        assert!(!frame(&mut c, "c", (16, 8), 2));
        assert_eq!(names(&c), ["c"]);
        // The same name at another size is mapped anew.
        assert!(!frame(&mut c, "c", (16, 16), 3));
        assert_eq!(names(&c), ["c"]);
    }

    #[test]
    fn at_most_keep_are_held() {
        let mut c = CanvasCache::default();
        for f in 0..10u64 {
            frame(&mut c, &format!("c{f}"), (8, 8), f);
            assert!(c.held().count() <= KEEP);
        }
        assert_eq!(c.held().count(), KEEP);
    }
}

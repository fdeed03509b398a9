//! Premultiplied RGBA partial images and the front-to-back OVER operator.
//!
//! A worker's output for its region is a [`PartialImage`]: the full image size plus the
//! rectangle that holds any content, and premultiplied linear RGBA `f32` pixels for that
//! rectangle only. Sort-last compositing consumes exactly this unit.

use serde::{Deserialize, Serialize};

/// A screen rectangle `[x0, y0, width, height]` in pixels (y = 0 is the top row).
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Rect {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Columns.
    pub w: u32,
    /// Rows.
    pub h: u32,
}

impl Rect {
    /// The empty rectangle.
    pub const EMPTY: Rect = Rect {
        x: 0,
        y: 0,
        w: 0,
        h: 0,
    };

    /// Whether the rectangle holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.w == 0 || self.h == 0
    }

    /// Number of pixels.
    pub fn area(&self) -> usize {
        self.w as usize * self.h as usize
    }

    /// The pixels `[x0, x1) × [y0, y1)` ([`Rect::EMPTY`] when that holds none).
    pub fn spanning(x0: u32, y0: u32, x1: u32, y1: u32) -> Rect {
        if x0 >= x1 || y0 >= y1 {
            return Rect::EMPTY;
        }
        Rect {
            x: x0,
            y: y0,
            w: x1 - x0,
            h: y1 - y0,
        }
    }

    /// The smallest rectangle holding both.
    pub fn union(&self, o: &Rect) -> Rect {
        if self.is_empty() {
            return *o;
        }
        if o.is_empty() {
            return *self;
        }
        let x0 = self.x.min(o.x);
        let y0 = self.y.min(o.y);
        let x1 = (self.x + self.w).max(o.x + o.w);
        let y1 = (self.y + self.h).max(o.y + o.h);
        Rect::spanning(x0, y0, x1, y1)
    }

    /// The pixels in both ([`Rect::EMPTY`] when they do not meet).
    pub fn intersect(&self, o: &Rect) -> Rect {
        let x0 = self.x.max(o.x);
        let y0 = self.y.max(o.y);
        let x1 = (self.x + self.w).min(o.x + o.w);
        let y1 = (self.y + self.h).min(o.y + o.h);
        Rect::spanning(x0, y0, x1, y1)
    }
}

/// Premultiplied RGBA.
pub type Rgba = [f32; 4];

/// `front OVER back` for premultiplied colours.
#[inline]
pub fn over(front: Rgba, back: Rgba) -> Rgba {
    let t = 1.0 - front[3];
    [
        front[0] + t * back[0],
        front[1] + t * back[1],
        front[2] + t * back[2],
        front[3] + t * back[3],
    ]
}

/// A region's premultiplied RGBA image: only the rectangle with content is stored.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PartialImage {
    /// Full image width.
    pub width: u32,
    /// Full image height.
    pub height: u32,
    /// Where the stored pixels sit; every pixel outside is transparent black.
    pub rect: Rect,
    /// `rect.w * rect.h` pixels, row-major.
    pub pixels: Vec<Rgba>,
}

impl PartialImage {
    /// A fully transparent image.
    pub fn empty(width: u32, height: u32) -> Self {
        PartialImage {
            width,
            height,
            rect: Rect::EMPTY,
            pixels: Vec::new(),
        }
    }

    /// Wraps a full-frame pixel array, shrinking the stored rectangle to the pixels with
    /// content (alpha or colour non-zero).
    pub fn from_full(width: u32, height: u32, full: &[Rgba]) -> Self {
        assert_eq!(full.len(), width as usize * height as usize);
        let (mut x0, mut y0, mut x1, mut y1) = (u32::MAX, u32::MAX, 0u32, 0u32);
        for y in 0..height {
            let row = &full[(y * width) as usize..((y + 1) * width) as usize];
            for (x, p) in row.iter().enumerate() {
                if p.iter().any(|&c| c != 0.0) {
                    x0 = x0.min(x as u32);
                    x1 = x1.max(x as u32 + 1);
                    y0 = y0.min(y);
                    y1 = y1.max(y + 1);
                }
            }
        }
        if x0 == u32::MAX {
            return Self::empty(width, height);
        }
        let rect = Rect {
            x: x0,
            y: y0,
            w: x1 - x0,
            h: y1 - y0,
        };
        let mut pixels = Vec::with_capacity(rect.area());
        for y in y0..y1 {
            let s = (y * width + x0) as usize;
            pixels.extend_from_slice(&full[s..s + rect.w as usize]);
        }
        PartialImage {
            width,
            height,
            rect,
            pixels,
        }
    }

    /// The pixel at full-image coordinates (transparent outside the rectangle).
    pub fn get(&self, x: u32, y: u32) -> Rgba {
        let r = &self.rect;
        if x < r.x || y < r.y || x >= r.x + r.w || y >= r.y + r.h {
            return [0.0; 4];
        }
        self.pixels[((y - r.y) * r.w + (x - r.x)) as usize]
    }

    /// Expands to a full-frame pixel array.
    pub fn to_full(&self) -> Vec<Rgba> {
        let mut full = vec![[0.0; 4]; self.width as usize * self.height as usize];
        let r = &self.rect;
        for row in 0..r.h {
            let d = ((r.y + row) * self.width + r.x) as usize;
            let s = (row * r.w) as usize;
            full[d..d + r.w as usize].copy_from_slice(&self.pixels[s..s + r.w as usize]);
        }
        full
    }

    /// Composites `self OVER back` (self in front) into a full-frame array.
    pub fn over_full(&self, back: &mut [Rgba]) {
        let r = &self.rect;
        for row in 0..r.h {
            for col in 0..r.w {
                let d = ((r.y + row) * self.width + r.x + col) as usize;
                back[d] = over(self.pixels[(row * r.w + col) as usize], back[d]);
            }
        }
    }
}

/// Serial reference: composites images given front to back into one full-frame array.
pub fn composite_front_to_back(
    width: u32,
    height: u32,
    front_to_back: &[&PartialImage],
) -> Vec<Rgba> {
    let mut acc = vec![[0.0f32; 4]; width as usize * height as usize];
    // Walk back to front so each image goes OVER what lies behind it.
    for img in front_to_back.iter().rev() {
        assert_eq!((img.width, img.height), (width, height));
        img.over_full(&mut acc);
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The intersection holds the pixels in both, and nothing for rectangles that only
    /// touch or miss.
    #[test]
    fn rectangles_intersect_in_the_pixels_of_both() {
        let a = Rect {
            x: 2,
            y: 3,
            w: 10,
            h: 5,
        };
        let b = Rect {
            x: 8,
            y: 0,
            w: 10,
            h: 5,
        };
        assert_eq!(
            a.intersect(&b),
            Rect {
                x: 8,
                y: 3,
                w: 4,
                h: 2
            }
        );
        assert_eq!(b.intersect(&a), a.intersect(&b));
        assert_eq!(a.intersect(&a), a);
        let touching = Rect {
            x: 12,
            y: 3,
            w: 4,
            h: 4,
        };
        assert!(a.intersect(&touching).is_empty());
        assert!(a.intersect(&Rect::EMPTY).is_empty());
    }

    #[test]
    fn over_is_associative() {
        let a = [0.2, 0.1, 0.0, 0.3];
        let b = [0.0, 0.4, 0.1, 0.5];
        let c = [0.3, 0.3, 0.3, 0.9];
        let l = over(over(a, b), c);
        let r = over(a, over(b, c));
        for i in 0..4 {
            assert!((l[i] - r[i]).abs() < 1e-6);
        }
    }

    #[test]
    fn crop_and_expand() {
        let mut full = vec![[0.0; 4]; 6 * 4];
        full[2 * 6 + 3] = [0.5, 0.0, 0.0, 0.5];
        full[3 * 6 + 1] = [0.0, 0.1, 0.0, 0.1];
        let p = PartialImage::from_full(6, 4, &full);
        assert_eq!(
            p.rect,
            Rect {
                x: 1,
                y: 2,
                w: 3,
                h: 2
            }
        );
        assert_eq!(p.to_full(), full);
        assert_eq!(p.get(3, 2), [0.5, 0.0, 0.0, 0.5]);
        assert!(PartialImage::from_full(6, 4, &vec![[0.0; 4]; 24])
            .rect
            .is_empty());
    }
}

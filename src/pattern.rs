//! Binary weave patterns `P` (docs/design.md §0): `n_e` rows (weft yarns, along image x) × `n_a`
//! columns (warp yarns, along image y); `P[i][j] = 1` means weft `i` lies over warp `j`.

use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::fmt;
use std::path::Path;

/// Largest pattern side accepted.
pub const MAX_SIDE: usize = 64;

/// Errors for malformed patterns.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PatternError {
    /// No rows or no columns.
    #[error("weave pattern is empty")]
    Empty,
    /// Rows of different lengths.
    #[error("weave pattern is ragged: row {row} has {len} cells, row 0 has {expected}")]
    Ragged {
        /// Offending row.
        row: usize,
        /// Its length.
        len: usize,
        /// Length of row 0.
        expected: usize,
    },
    /// A character other than 0/1.
    #[error("weave pattern has a non-binary cell {found:?} at row {row}, column {col} (only 0 and 1 allowed)")]
    NonBinary {
        /// Row.
        row: usize,
        /// Column.
        col: usize,
        /// The character found.
        found: char,
    },
    /// More than 64 rows or columns.
    #[error("weave pattern is {rows}x{cols}; at most {MAX_SIDE}x{MAX_SIDE} is supported")]
    TooLarge {
        /// Rows.
        rows: usize,
        /// Columns.
        cols: usize,
    },
    /// Unknown preset name.
    #[error("unknown weave preset `{0}`; known: plain, basket2, twill21, twill22, twill31, satin4, satin5, satin8")]
    UnknownPreset(String),
    /// Image could not be read.
    #[error("cannot read pattern image: {0}")]
    Image(String),
    /// A yarn never changes side, so it floats over (or under) the whole fabric, held by nothing.
    #[error(
        "weave pattern {pattern} is not woven: {yarn} {index} lies {side} every {other} (its {line} is all {bit}), so it would float over the whole fabric; every row and every column needs both a 0 and a 1"
    )]
    Floating {
        /// The pattern, as rows `1100/0110/…`.
        pattern: String,
        /// `weft` or `warp`.
        yarn: &'static str,
        /// Row (weft) or column (warp) index.
        index: usize,
        /// `over` or `under`.
        side: &'static str,
        /// The crossing family (`warp` for a weft, `weft` for a warp).
        other: &'static str,
        /// `row` or `column`.
        line: &'static str,
        /// The repeated cell value, `1` or `0`.
        bit: u8,
    },
}

/// A binary weave pattern, always stored reduced to its minimum repeat.
#[derive(Clone, PartialEq, Eq, Hash)]
pub struct WeavePattern {
    rows: usize,
    cols: usize,
    cells: Vec<bool>,
}

/// Names of the built-in presets.
pub const PRESETS: &[&str] = &["plain", "basket2", "twill21", "twill22", "twill31", "satin4", "satin5", "satin8"];

impl WeavePattern {
    /// Build from rows of booleans; validates and reduces to the minimum repeat.
    pub fn from_rows(rows: &[Vec<bool>]) -> Result<Self, PatternError> {
        let p = Self::from_rows_unreduced(rows)?;
        Ok(p.reduced())
    }

    /// Build without reducing (for tiles that must keep their size).
    pub fn from_rows_unreduced(rows: &[Vec<bool>]) -> Result<Self, PatternError> {
        if rows.is_empty() || rows[0].is_empty() {
            return Err(PatternError::Empty);
        }
        let cols = rows[0].len();
        for (i, r) in rows.iter().enumerate() {
            if r.len() != cols {
                return Err(PatternError::Ragged { row: i, len: r.len(), expected: cols });
            }
        }
        if rows.len() > MAX_SIDE || cols > MAX_SIDE {
            return Err(PatternError::TooLarge { rows: rows.len(), cols });
        }
        Ok(WeavePattern { rows: rows.len(), cols, cells: rows.concat() })
    }

    /// Parse `1100/0110/0011/1001` (rows separated by `/`, `,`, `;` or newlines; spaces ignored),
    /// reduced to the minimum repeat.
    pub fn parse(text: &str) -> Result<Self, PatternError> {
        Ok(Self::parse_unreduced(text)?.reduced())
    }

    /// [`WeavePattern::parse`] keeping the tile as written: a parameter file's pattern is the tile
    /// its body texture is laid over (a yarn-dyed stripe repeats over more yarns than the weave).
    pub fn parse_unreduced(text: &str) -> Result<Self, PatternError> {
        let mut rows = Vec::new();
        for line in text.split(['/', ',', ';', '\n']) {
            let line: String = line.chars().filter(|c| !c.is_whitespace()).collect();
            if line.is_empty() {
                continue;
            }
            let mut row = Vec::new();
            for (col, ch) in line.chars().enumerate() {
                match ch {
                    '0' => row.push(false),
                    '1' => row.push(true),
                    found => return Err(PatternError::NonBinary { row: rows.len(), col, found }),
                }
            }
            rows.push(row);
        }
        Self::from_rows_unreduced(&rows)
    }

    /// Resolve a command-line spec: a preset name, a text grid, a text file of 0/1 rows, or a PNG.
    pub fn from_spec(spec: &str) -> Result<Self, PatternError> {
        if PRESETS.contains(&spec) {
            return Self::preset(spec);
        }
        let path = Path::new(spec);
        if path.is_file() {
            let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_lowercase();
            if ext == "png" || ext == "jpg" || ext == "jpeg" {
                return Self::from_image(path);
            }
            let text = std::fs::read_to_string(path).map_err(|e| PatternError::Image(e.to_string()))?;
            return Self::parse(&text);
        }
        if spec.chars().all(|c| "01/,;\n ".contains(c)) {
            return Self::parse(spec);
        }
        Err(PatternError::UnknownPreset(spec.to_string()))
    }

    /// Threshold a (grey) image at its mean: bright pixel = weft over (custom/logo patterns).
    pub fn from_image(path: &Path) -> Result<Self, PatternError> {
        let img = image::open(path).map_err(|e| PatternError::Image(e.to_string()))?.to_luma8();
        let (w, h) = img.dimensions();
        if w as usize > MAX_SIDE || h as usize > MAX_SIDE {
            return Err(PatternError::TooLarge { rows: h as usize, cols: w as usize });
        }
        let mean = img.pixels().map(|p| p.0[0] as f64).sum::<f64>() / (w * h).max(1) as f64;
        let rows: Vec<Vec<bool>> =
            (0..h).map(|y| (0..w).map(|x| img.get_pixel(x, y).0[0] as f64 > mean).collect()).collect();
        Self::from_rows(&rows)
    }

    /// Built-in presets (and `NAME` rotated by 90° via [`WeavePattern::rotated90`]).
    pub fn preset(name: &str) -> Result<Self, PatternError> {
        let (n, f): (usize, Box<dyn Fn(usize, usize) -> bool>) = match name {
            "plain" => (2, Box::new(|i, j| (i + j) % 2 == 0)),
            "basket2" => (4, Box::new(|i, j| (i / 2 + j / 2) % 2 == 0)),
            "twill21" => (3, Box::new(|i, j| (j + 3 - i % 3) % 3 < 2)),
            "twill22" => (4, Box::new(|i, j| (j + 4 - i % 4) % 4 < 2)),
            "twill31" => (4, Box::new(|i, j| (j + 4 - i % 4) % 4 < 3)),
            // 4-end broken "satin" (crowfoot): one binding point per row at columns 0, 1, 3, 2.
            "satin4" => (4, Box::new(|i, j| j != [0, 1, 3, 2][i])),
            "satin5" => (5, Box::new(|i, j| j != (i * 2) % 5)),
            "satin8" => (8, Box::new(|i, j| j != (i * 3) % 8)),
            other => return Err(PatternError::UnknownPreset(other.to_string())),
        };
        let rows: Vec<Vec<bool>> = (0..n).map(|i| (0..n).map(|j| f(i, j)).collect()).collect();
        Self::from_rows(&rows)
    }

    /// Rotate by 90°: wefts become warps (transpose, then invert so "weft over" keeps its meaning
    /// for the new wefts).
    pub fn rotated90(&self) -> Self {
        let rows: Vec<Vec<bool>> =
            (0..self.cols).map(|j| (0..self.rows).map(|i| !self.get(self.rows - 1 - i, j)).collect()).collect();
        Self::from_rows(&rows).expect("rotation keeps a valid pattern")
    }

    /// `n_e`: number of weft yarns in the repeat.
    pub fn n_e(&self) -> usize {
        self.rows
    }

    /// `n_a`: number of warp yarns in the repeat.
    pub fn n_a(&self) -> usize {
        self.cols
    }

    /// `P[i][j]`, indices taken modulo the repeat.
    pub fn get(&self, i: usize, j: usize) -> bool {
        self.cells[(i % self.rows) * self.cols + j % self.cols]
    }

    /// Flip one cell (for the annealer).
    pub fn toggled(&self, i: usize, j: usize) -> Self {
        let mut p = self.clone();
        let k = i * self.cols + j;
        p.cells[k] = !p.cells[k];
        p
    }

    /// Every cell flipped: the same cloth seen from the back (weft and warp swap who is on top).
    pub fn inverted(&self) -> Self {
        let mut p = self.clone();
        p.cells.iter_mut().for_each(|c| *c = !*c);
        p
    }

    /// Rows as booleans.
    pub fn rows(&self) -> Vec<Vec<bool>> {
        (0..self.rows).map(|i| (0..self.cols).map(|j| self.get(i, j)).collect()).collect()
    }

    /// Smallest (rows', cols') with rows' | rows, cols' | cols such that P repeats with that period.
    pub fn reduced(&self) -> Self {
        let r = (1..=self.rows)
            .find(|&p| {
                self.rows.is_multiple_of(p)
                    && (0..self.rows).all(|i| (0..self.cols).all(|j| self.get(i, j) == self.get(i + p, j)))
            })
            .unwrap_or(self.rows);
        let c = (1..=self.cols)
            .find(|&p| {
                self.cols.is_multiple_of(p)
                    && (0..self.rows).all(|i| (0..self.cols).all(|j| self.get(i, j) == self.get(i, j + p)))
            })
            .unwrap_or(self.cols);
        let rows: Vec<Vec<bool>> = (0..r).map(|i| (0..c).map(|j| self.get(i, j)).collect()).collect();
        WeavePattern { rows: r, cols: c, cells: rows.concat() }
    }

    /// Equal up to a cyclic shift (the same fabric with another origin).
    pub fn equivalent(&self, other: &Self) -> bool {
        if self.rows != other.rows || self.cols != other.cols {
            return false;
        }
        (0..self.rows).any(|di| {
            (0..self.cols)
                .any(|dj| (0..self.rows).all(|i| (0..self.cols).all(|j| self.get(i + di, j + dj) == other.get(i, j))))
        })
    }

    /// Whether this is a herringbone (Watson, "Textile Design and Colour", docs/bibliography.md: the point, broken
    /// and reversed twills): a twill whose diagonal turns back every `r` yarns, `r ≥`
    /// [`herringbone_min_run`] (3, and about the twill's own repeat). On the minimum repeat, along the wefts (or the warps, transposed): `2r` rows, each
    /// of the first `r` the previous one moved on by one yarn, each of the next `r` moved back by
    /// one (`P[k+1][j] = P[k][j ∓ 1]`), the two turns free (where they break the diagonal, a
    /// broken herringbone; where they mirror it, a pointed one), the twill side (the other
    /// count) at least 3. Invariant under cyclic shifts, inversion and mirroring.
    pub fn is_herringbone(&self) -> bool {
        herringbone_repeat(&self.reduced())
    }

    /// `true` when some weft or warp never changes side: it would float over the whole fabric.
    pub fn has_unbound_yarn(&self) -> bool {
        let weft = (0..self.rows).any(|i| (0..self.cols).all(|j| self.get(i, j) == self.get(i, 0)));
        let warp = (0..self.cols).any(|j| (0..self.rows).all(|i| self.get(i, j) == self.get(0, j)));
        weft || warp
    }
}

/// Shortest run of rows a herringbone's diagonal keeps one direction ([`WeavePattern::is_herringbone`]):
/// three yarns make a visible diagonal; a turn after every second yarn is a zigzag of short
/// floats that reads as a broken basket, not a herringbone.
pub const HERRINGBONE_MIN_RUN: usize = 3;

/// Shortest run `r` of a herringbone on a twill of side `n`: [`HERRINGBONE_MIN_RUN`], and at
/// least `n − 1` yarns, so that each run shows about one repeat of its twill (the point and
/// reversed twills of the textbooks). Shorter runs make a figured zigzag; they would also make
/// thousands of square-grid patterns (a 6-twill turning every 3 yarns) "named", diluting what
/// naming tells the fit.
pub fn herringbone_min_run(n: usize) -> usize {
    HERRINGBONE_MIN_RUN.max(n.saturating_sub(1))
}

/// [`WeavePattern::is_herringbone`] of a minimum repeat `p`: along its rows or its columns.
fn herringbone_repeat(p: &WeavePattern) -> bool {
    let columns: Vec<Vec<bool>> = (0..p.cols).map(|j| (0..p.rows).map(|i| p.get(i, j)).collect()).collect();
    herringbone_rows(&p.rows()) || herringbone_rows(&columns)
}

/// Whether `rows` (cyclic, `2r` of them, each of length `n ≥ 3`) is a herringbone along the
/// rows: from some starting row, `r − 1` steps of the diagonal one way (each row the previous
/// moved on by one yarn), then `r − 1` steps back, the two turns free.
fn herringbone_rows(rows: &[Vec<bool>]) -> bool {
    let (m, n) = (rows.len(), rows.first().map_or(0, Vec::len));
    if n < 3 || !m.is_multiple_of(2) || m / 2 < herringbone_min_run(n) {
        return false;
    }
    let r = m / 2;
    // `rows[b]` is `rows[a]` moved on by `d` yarns: `rows[b][j] = rows[a][j − d]`.
    let moved = |a: usize, b: usize, d: isize| {
        (0..n).all(|j| rows[b % m][j] == rows[a % m][(j as isize - d).rem_euclid(n as isize) as usize])
    };
    (0..m).any(|s| {
        [1isize, -1]
            .iter()
            .any(|&d| (s..s + r - 1).all(|k| moved(k, k + 1, d)) && (s + r..s + 2 * r - 1).all(|k| moved(k, k + 1, -d)))
    })
}

/// The weave class of a pattern, as fabric labels name it ([`WeavePattern::weave_class`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum WeaveClass {
    /// Plain (tabby): the 2×2 checker.
    Plain,
    /// Twill: square repeat of side ≥ 3 whose rows step by ±1 yarn (one diagonal of floats),
    /// and its herringbones (the diagonal turning back, [`WeavePattern::is_herringbone`]).
    Twill,
    /// Satin (or sateen): square repeat of side ≥ 4 with one binding point per row and per
    /// column that does not step by ±1 (the 4-end crowfoot, steps 1, 2, −1, −2, included).
    Satin,
    /// Basket (hopsack): the plain weave with every cell a k×k block, k ≥ 2.
    Basket,
    /// Anything else (ribs, broken or figured weaves, patterns with a floating yarn).
    Other,
}

impl WeaveClass {
    /// Every class, in the order of the enum.
    pub const ALL: [WeaveClass; 5] =
        [WeaveClass::Plain, WeaveClass::Twill, WeaveClass::Satin, WeaveClass::Basket, WeaveClass::Other];

    /// Lower-case name (`plain`, `twill`, `satin`, `basket`, `other`).
    pub fn name(self) -> &'static str {
        match self {
            WeaveClass::Plain => "plain",
            WeaveClass::Twill => "twill",
            WeaveClass::Satin => "satin",
            WeaveClass::Basket => "basket",
            WeaveClass::Other => "other",
        }
    }
}

impl fmt::Display for WeaveClass {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A weave-class name that is none of [`WeaveClass::ALL`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown weave class `{0}` (known: plain, twill, satin, basket, other)")]
pub struct UnknownClass(pub String);

impl std::str::FromStr for WeaveClass {
    type Err = UnknownClass;
    /// Case-insensitive; `tabby` is plain, `sateen` is satin, `hopsack` is basket.
    fn from_str(s: &str) -> Result<Self, UnknownClass> {
        match s.trim().to_ascii_lowercase().as_str() {
            "plain" | "tabby" => Ok(WeaveClass::Plain),
            "twill" => Ok(WeaveClass::Twill),
            "satin" | "sateen" => Ok(WeaveClass::Satin),
            "basket" | "hopsack" => Ok(WeaveClass::Basket),
            "other" => Ok(WeaveClass::Other),
            _ => Err(UnknownClass(s.to_string())),
        }
    }
}

impl WeavePattern {
    /// The weave class of the fabric this pattern makes ([`WeaveClass`]). The class depends only
    /// on the cloth, not on how it is seen: it is the same for every cyclic shift, for the
    /// inverted pattern (the back of the cloth), the transposed one ([`WeavePattern::rotated90`])
    /// and the mirrored ones, because every test below is invariant under these.
    ///
    /// On the minimum repeat (`n × m`): a herringbone ([`WeavePattern::is_herringbone`]) is a
    /// twill (textbook and fabric labels file it so); a floating yarn or `n ≠ m` is `Other`; `2 × 2` is plain
    /// (the only woven 2×2 is the checker); `2k × 2k` equal to the checker of `k × k` blocks up
    /// to shift and inversion is basket; otherwise, when every row is the previous one shifted
    /// by the same step `s` (`P[i+1][j+s] = P[i][j]`), `s = ±1` with `n ≥ 3` is a twill; a square
    /// repeat of side ≥ 4 whose rows and columns each hold one cell unlike the others (one
    /// binding point) and that is not such a twill is a satin.
    pub fn weave_class(&self) -> WeaveClass {
        let p = self.reduced();
        let n = p.rows;
        if p.has_unbound_yarn() {
            return WeaveClass::Other;
        }
        if herringbone_repeat(&p) {
            return WeaveClass::Twill;
        }
        if n != p.cols {
            return WeaveClass::Other;
        }
        if n == 2 {
            return WeaveClass::Plain;
        }
        if n.is_multiple_of(2) {
            let k = n / 2;
            let blocks: Vec<Vec<bool>> =
                (0..n).map(|i| (0..n).map(|j| (i / k + j / k).is_multiple_of(2)).collect()).collect();
            let b = WeavePattern { rows: n, cols: n, cells: blocks.concat() };
            if p.equivalent(&b) || p.equivalent(&b.inverted()) {
                return WeaveClass::Basket;
            }
        }
        let steps = |s: usize| (0..n).all(|i| (0..n).all(|j| p.get(i + 1, j + s) == p.get(i, j)));
        if steps(1) || steps(n - 1) {
            return WeaveClass::Twill;
        }
        // One binding point: exactly one cell of the line differs from the others.
        let single = |count: usize| count == 1 || count == n - 1;
        let rows_single = (0..n).all(|i| single((0..n).filter(|&j| p.get(i, j)).count()));
        let cols_single = (0..n).all(|j| single((0..n).filter(|&i| p.get(i, j)).count()));
        if n >= 4 && rows_single && cols_single {
            return WeaveClass::Satin;
        }
        WeaveClass::Other
    }
}

impl WeavePattern {
    /// Check that the pattern is a woven cloth: every weft changes side at least once across the
    /// warps and every warp across the wefts. A yarn that never does (an all-ones or all-zeros row
    /// or column) floats over the whole fabric, which no loom makes and the renderer cannot hold
    /// in place; the error names the first such yarn. Used on user input (parameter files, the
    /// `params`, `render` and `export` commands) and deliberately not in the constructors: the fit
    /// builds and scores such candidates internally.
    pub fn check_woven(&self) -> Result<(), PatternError> {
        let floating = |yarn, index, first: bool| {
            let (other, line) = if yarn == "weft" { ("warp", "row") } else { ("weft", "column") };
            // Cell 1 means weft over warp: a weft row of 1s lies over, a warp column of 1s under.
            let over = first == (yarn == "weft");
            Err(PatternError::Floating {
                pattern: self.to_string(),
                yarn,
                index,
                side: if over { "over" } else { "under" },
                other,
                line,
                bit: first as u8,
            })
        };
        if let Some(i) = (0..self.rows).find(|&i| (0..self.cols).all(|j| self.get(i, j) == self.get(i, 0))) {
            return floating("weft", i, self.get(i, 0));
        }
        if let Some(j) = (0..self.cols).find(|&j| (0..self.rows).all(|i| self.get(i, j) == self.get(0, j))) {
            return floating("warp", j, self.get(0, j));
        }
        Ok(())
    }
}

/// A command-line pattern spec, as [`WeavePattern::from_spec`]: a preset name, a text grid
/// (`1100/0110/…`), or the path of a 0/1 text file or an image.
impl std::str::FromStr for WeavePattern {
    type Err = PatternError;
    fn from_str(spec: &str) -> Result<Self, PatternError> {
        Self::from_spec(spec)
    }
}

impl fmt::Display for WeavePattern {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s: Vec<String> =
            self.rows().iter().map(|r| r.iter().map(|&b| if b { '1' } else { '0' }).collect()).collect();
        write!(f, "{}", s.join("/"))
    }
}

impl fmt::Debug for WeavePattern {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "WeavePattern({self})")
    }
}

impl Serialize for WeavePattern {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let rows: Vec<String> = self.to_string().split('/').map(str::to_string).collect();
        rows.serialize(s)
    }
}

impl<'de> Deserialize<'de> for WeavePattern {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let rows = Vec::<String>::deserialize(d)?;
        WeavePattern::parse_unreduced(&rows.join("/")).map_err(|e| serde::de::Error::custom(format!("pattern: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn weave_classes_of_the_presets_and_their_views() {
        use WeaveClass::*;
        let want = [Plain, Basket, Twill, Twill, Twill, Satin, Satin, Satin];
        for (name, class) in PRESETS.iter().zip(want) {
            let p = WeavePattern::preset(name).unwrap();
            assert_eq!(p.weave_class(), class, "{name}: {p}");
            // The same cloth seen shifted, from the back, turned by 90° and mirrored.
            let shifted: Vec<Vec<bool>> =
                (0..p.n_e()).map(|i| (0..p.n_a()).map(|j| p.get(i + 1, j + 2)).collect()).collect();
            let mirrored: Vec<Vec<bool>> = p.rows().into_iter().rev().collect();
            for (view, q) in [
                ("shifted", WeavePattern::from_rows(&shifted).unwrap()),
                ("inverted", p.inverted()),
                ("rotated", p.rotated90()),
                ("mirrored", WeavePattern::from_rows(&mirrored).unwrap()),
            ] {
                assert_eq!(q.weave_class(), class, "{name} {view}: {q}");
            }
            // A repeat stored twice over (unreduced) is the same class.
            let big: Vec<Vec<bool>> =
                (0..2 * p.n_e()).map(|i| (0..2 * p.n_a()).map(|j| p.get(i, j)).collect()).collect();
            assert_eq!(WeavePattern::from_rows_unreduced(&big).unwrap().weave_class(), class, "{name} doubled");
        }
    }

    #[test]
    fn weave_classes_of_other_patterns() {
        use WeaveClass::*;
        let class = |s: &str| WeavePattern::parse(s).unwrap().weave_class();
        // A 3×3 basket, a 3/1 broken twill (steps +1, +1, −1… no constant step) and a 2/1/1/2 twill.
        assert_eq!(class("111000/111000/111000/000111/000111/000111"), Basket);
        assert_eq!(class("11010/01101/10110/01011/10101"), Twill);
        assert_eq!(class("1110/1101/1011/0111"), Twill);
        // Satin 7 with step 3; a rib (2×4) and a half basket are not square → other.
        let satin7: Vec<Vec<bool>> = (0..7).map(|i| (0..7).map(|j| j != (3 * i) % 7).collect()).collect();
        assert_eq!(WeavePattern::from_rows(&satin7).unwrap().weave_class(), Satin);
        assert_eq!(class("1100/0011"), Other);
        // A floating yarn is not a weave; a random 4×4 weave is other.
        assert_eq!(class("1111/0101/1010/0101"), Other);
        assert_eq!(class("1100/0110/1011/1001"), Other);
        // Names parse case-insensitively, with the usual synonyms; unknown names are refused.
        assert_eq!("Twill".parse::<WeaveClass>(), Ok(Twill));
        assert_eq!("sateen".parse::<WeaveClass>(), Ok(Satin));
        assert_eq!("tabby".parse::<WeaveClass>(), Ok(Plain));
        assert!("jacquard".parse::<WeaveClass>().unwrap_err().to_string().contains("known: plain"));
        assert_eq!(Satin.to_string(), "satin");
    }

    #[test]
    fn presets_are_valid_and_minimal() {
        let sizes = [2, 4, 3, 4, 4, 4, 5, 8];
        for (name, n) in PRESETS.iter().zip(sizes) {
            let p = WeavePattern::preset(name).unwrap();
            assert_eq!((p.n_e(), p.n_a()), (n, n), "{name}: {p}");
            assert!(!p.has_unbound_yarn(), "{name} has a floating yarn: {p}");
        }
        assert_eq!(WeavePattern::preset("plain").unwrap().to_string(), "10/01");
        assert_eq!(WeavePattern::preset("twill22").unwrap().to_string(), "1100/0110/0011/1001");
    }

    #[test]
    fn floating_yarns_are_named() {
        for name in PRESETS {
            WeavePattern::preset(name).unwrap().check_woven().unwrap();
        }
        let e = WeavePattern::parse("11/11").unwrap().check_woven().unwrap_err().to_string();
        assert!(e.contains("weft 0 lies over every warp") && e.contains("row is all 1"), "{e}");
        let e = WeavePattern::parse("10/10").unwrap().check_woven().unwrap_err().to_string();
        assert!(e.contains("warp 0 lies under every weft") && e.contains("column is all 1"), "{e}");
        let e = WeavePattern::parse("110/011/000").unwrap().check_woven().unwrap_err().to_string();
        assert!(e.contains("weft 2 lies under every warp"), "{e}");
        let p: WeavePattern = "twill22".parse().unwrap();
        assert_eq!(p, WeavePattern::preset("twill22").unwrap());
        assert!("herringbone".parse::<WeavePattern>().is_err());
    }

    #[test]
    fn satin_has_one_binding_point_per_row_and_column() {
        for name in ["satin4", "satin5", "satin8"] {
            let p = WeavePattern::preset(name).unwrap();
            for i in 0..p.n_e() {
                assert_eq!((0..p.n_a()).filter(|&j| !p.get(i, j)).count(), 1, "{name} row {i}");
            }
            for j in 0..p.n_a() {
                assert_eq!((0..p.n_e()).filter(|&i| !p.get(i, j)).count(), 1, "{name} col {j}");
            }
        }
    }

    #[test]
    fn parse_reduce_and_errors() {
        let p = WeavePattern::parse("1010/0101/1010/0101").unwrap();
        assert_eq!(p.to_string(), "10/01");
        assert_eq!(WeavePattern::parse(""), Err(PatternError::Empty));
        assert!(matches!(WeavePattern::parse("10/1"), Err(PatternError::Ragged { row: 1, .. })));
        assert!(matches!(WeavePattern::parse("12/01"), Err(PatternError::NonBinary { found: '2', .. })));
        let big = vec!["01".repeat(33); 2].join("/");
        assert!(matches!(WeavePattern::parse(&big), Err(PatternError::TooLarge { .. })));
        assert!(WeavePattern::from_spec("nonsense").is_err());
    }

    #[test]
    fn png_patterns_are_thresholded_and_reduced() {
        let dir = std::env::temp_dir().join(format!("woven-pattern-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("logo.png");
        // A 6×6 image repeating a 3×3 logo: bright = weft over.
        let logo = [[1, 0, 0], [1, 1, 0], [0, 1, 1]];
        let img = image::GrayImage::from_fn(6, 6, |x, y| {
            image::Luma([if logo[y as usize % 3][x as usize % 3] == 1 { 230 } else { 20 }])
        });
        img.save(&path).unwrap();
        let p = WeavePattern::from_spec(path.to_str().unwrap()).unwrap();
        assert_eq!(p.to_string(), "100/110/011");
        let big = image::GrayImage::from_fn(65, 2, |x, _| image::Luma([(x % 2 * 255) as u8]));
        big.save(&path).unwrap();
        assert!(matches!(WeavePattern::from_spec(path.to_str().unwrap()), Err(PatternError::TooLarge { .. })));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn rotation_and_equivalence() {
        let t = WeavePattern::preset("twill31").unwrap();
        let r = t.rotated90();
        assert_eq!((r.n_e(), r.n_a()), (4, 4));
        assert!(!r.has_unbound_yarn());
        assert!(r.rotated90().rotated90().rotated90() == t);
        let shifted = WeavePattern::parse("0110/0011/1001/1100").unwrap();
        assert!(shifted.equivalent(&WeavePattern::preset("twill22").unwrap()));
    }

    #[test]
    fn inverting_twice_is_the_identity_and_swaps_every_cell() {
        let p = WeavePattern::parse("1110/0100/1011/0001").expect("pattern");
        let q = p.inverted();
        for i in 0..4 {
            for j in 0..4 {
                assert_ne!(p.get(i, j), q.get(i, j));
            }
        }
        assert_eq!(q.inverted(), p);
    }
}

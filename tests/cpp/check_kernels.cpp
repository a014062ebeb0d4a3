// check_core's checks of the sector, search and convolution kernels (check_core.cpp
// calls check_kernels after its own), compared between the native and aarch64 builds
// by `make check-aarch64`.
//
// - Kernels whose headers promise the same bits at every SIMD level (sector_fft,
//   sector_correlation, recentre_curves and recentre_places, exact_search,
//   projected_search) run at every level this CPU has, must agree to the bit, and
//   print a hash of their outputs: any difference between x86-64 and aarch64 shows in
//   the diff. Each is also held against a reference written here (double precision;
//   for projected_approx its exact definition, fused multiply-adds in axis order).
// - smallest_per_row against a full sort; the convolutions (direct and Winograd, sums
//   in orders of their own) against a double-precision reference, "ok" within a bound.
// - The invalid sizes the headers promise an exception for throw it.
// Lines starting with '#' (which kernels ran here, the convolutions' error sizes) are
// left out of the comparison.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "check_common.hpp"
#include "disco/conv3x3.hpp"
#include "disco/conv3x3_winograd.hpp"
#include "disco/exact_search.hpp"
#include "disco/polar_bev.hpp"
#include "disco/projected_search.hpp"
#include "disco/recentre_curves.hpp"
#include "disco/recentre_places.hpp"
#include "disco/row_selection.hpp"
#include "disco/sector_correlation.hpp"
#include "disco/sector_fft.hpp"

namespace disco_check {
namespace {

int failures = 0;
std::uint64_t* checksum_out = nullptr;
const double kPi = 3.14159265358979323846;

void expect(bool ok, const std::string& what) {
    if (!ok) {
        std::fprintf(stderr, "FAIL %s\n", what.c_str());
        ++failures;
    }
}

unsigned long long reported(std::uint64_t h) {
    *checksum_out = fnv1a(&h, sizeof h, *checksum_out);
    return static_cast<unsigned long long>(h);
}

template <typename T>
std::uint64_t hash_of(const std::vector<T>& v, std::uint64_t h = 1469598103934665603ull) {
    return fnv1a(v.data(), v.size() * sizeof(T), h);
}

template <typename T>
bool same_bits(const std::vector<T>& a, const std::vector<T>& b) {
    return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0;
}

std::vector<float> random_floats(std::uint64_t seed, std::size_t n, double lo, double hi) {
    Rng rng{seed};
    std::vector<float> v(n);
    for (auto& x : v) x = static_cast<float>(rng.uniform(lo, hi));
    return v;
}

// Runs `kernel` (returning its outputs' hash) at every level this CPU has, from the
// best down: every level must give the best one's bits. Returns that hash.
template <typename Kernel>
std::uint64_t at_every_level(const std::string& name, Kernel kernel) {
    const int best = disco::bev_kernel_level();
    std::uint64_t first = 0;
    for (int level = best; level >= 0; --level) {
        disco::set_bev_kernel_level(level);
        const std::uint64_t h = kernel();
        if (level == best) first = h;
        expect(h == first, name + ": level " + disco::bev_kernel_name(level) +
                               " differs from level " + disco::bev_kernel_name(best));
    }
    disco::set_bev_kernel_level(3);
    return first;
}

template <typename Exception, typename Call>
void expect_throw(const char* what, Call call) {
    bool thrown = false;
    try {
        call();
    } catch (const Exception&) {
        thrown = true;
    }
    expect(thrown, std::string("hostile: ") + what);
}

// ---- sector_fft: the rfft and irfft of rows, against a DFT in double ----
void check_sector_fft() {
    const std::int64_t rows = 19;  // one whole vector of 16 rows and a tail of 3
    std::uint64_t all = 1469598103934665603ull;
    int lengths = 0;
    for (int n : {1, 2, 3, 4, 5, 6, 7, 8, 9, 11, 12, 13, 15, 16, 17, 25, 27, 30, 49, 60, 64, 97,
                  120, 121, 360, 1024}) {
        const std::int64_t bins = n / 2 + 1;
        const std::vector<float> in = random_floats(1000 + n, rows * n, -4, 4);
        std::vector<float> spec(2 * rows * bins), back(rows * n);
        const std::uint64_t h = at_every_level("sector_fft n " + std::to_string(n), [&] {
            disco::rfft_rows(in.data(), rows, n, spec.data());
            disco::irfft_rows(spec.data(), rows, n, back.data());
            return hash_of(back, hash_of(spec));
        });
        double err = 0.0, back_err = 0.0;
        for (std::int64_t r = 0; r < rows; ++r) {
            const float* x = in.data() + r * n;
            double scale = 0.0;
            for (int s = 0; s < n; ++s) scale += std::abs(x[s]);
            for (std::int64_t k = 0; k < bins; ++k) {
                double re = 0.0, im = 0.0;
                for (int s = 0; s < n; ++s) {
                    const double a = -2.0 * kPi * static_cast<double>((k * s) % n) / n;
                    re += x[s] * std::cos(a);
                    im += x[s] * std::sin(a);
                }
                const float* got = spec.data() + 2 * (r * bins + k);
                err = std::max(err, std::hypot(got[0] - re, got[1] - im) / scale);
            }
            for (int s = 0; s < n; ++s)
                back_err = std::max(back_err, std::abs(back[r * n + s] - x[s]) / scale);
        }
        expect(err < 1e-6 && back_err < 1e-6,
               "sector_fft n " + std::to_string(n) + ": far from the DFT or not inverted");
        all = fnv1a(&h, sizeof h, all);
        ++lengths;
    }
    std::printf("sector_fft                   lengths %d rows %lld hash %016llx\n", lengths,
                static_cast<long long>(rows), reported(all));
    float dummy[4] = {0, 0, 0, 0};
    expect_throw<std::invalid_argument>("rfft of length 0", [&] { disco::rfft_rows(dummy, 1, 0, dummy); });
    expect_throw<std::invalid_argument>("rfft past 2^20",
                                        [&] { disco::rfft_rows(dummy, 0, (1 << 20) + 1, dummy); });
    expect_throw<std::invalid_argument>("rfft of -1 rows", [&] { disco::rfft_rows(dummy, -1, 2, dummy); });
    expect_throw<std::invalid_argument>("irfft of length 0", [&] { disco::irfft_rows(dummy, 1, 0, dummy); });
    expect_throw<std::invalid_argument>("irfft of -1 rows", [&] { disco::irfft_rows(dummy, -1, 2, dummy); });
}

// ---- sector_correlation ----
// The peak over circular shifts of the centred images' correlation, in double.
double reference_aligned(const float* q, const float* c, int rings, int sectors) {
    const int n = rings * sectors;
    double mq = 0.0, mc = 0.0;
    for (int i = 0; i < n; ++i) mq += q[i], mc += c[i];
    mq /= n, mc /= n;
    double nq = 0.0, nc = 0.0;
    for (int i = 0; i < n; ++i) nq += (q[i] - mq) * (q[i] - mq), nc += (c[i] - mc) * (c[i] - mc);
    if (nq == 0.0 || nc == 0.0) return 0.0;
    double best = -1e300;
    for (int t = 0; t < sectors; ++t) {
        double sum = 0.0;
        for (int r = 0; r < rings; ++r)
            for (int s = 0; s < sectors; ++s)
                sum += (q[r * sectors + s] - mq) * (c[r * sectors + (s + t) % sectors] - mc);
        best = std::max(best, sum);
    }
    return std::max(-1.0, std::min(1.0, best / std::sqrt(nq * nc)));
}

void check_sector_correlation() {
    const int rings = 5, sectors = 60, views = 3, count = 21;
    const std::int64_t cells = rings * sectors, stride = cells + 5;
    const std::vector<float> queries = random_floats(31, views * cells, 0, 2);
    std::vector<float> cands = random_floats(32, count * stride, 0, 2);
    // Candidate 4: query 1 turned by 7 sectors, 5: query 0 (yaw_curves' query) turned by
    // 11 (peaks of 1); candidate 9 all one value (a zero norm).
    for (int r = 0; r < rings; ++r)
        for (int s = 0; s < sectors; ++s) {
            cands[4 * stride + r * sectors + (s + 7) % sectors] = queries[cells + r * sectors + s];
            cands[5 * stride + r * sectors + (s + 11) % sectors] = queries[r * sectors + s];
        }
    std::fill(cands.begin() + 9 * stride, cands.begin() + 9 * stride + cells, 0.75f);
    std::vector<const float*> at(count);
    for (int k = 0; k < count; ++k) at[k] = cands.data() + k * stride;
    const std::vector<float> weights = {1.0f, 0.5f, 2.0f, 0.25f, 1.5f};
    std::vector<float> scores(views * count), scores_at(views * count), curves(count * sectors);
    std::vector<float> yaws(count), confs(count);
    const std::uint64_t h = at_every_level("sector_correlation", [&] {
        disco::aligned_correlations(queries.data(), views, cands.data(), count, stride, rings,
                                    sectors, scores.data());
        disco::aligned_correlations_at(queries.data(), views, at.data(), count, rings, sectors,
                                       scores_at.data());
        expect(same_bits(scores, scores_at), "aligned_correlations_at != aligned_correlations");
        disco::yaw_curves(queries.data(), cands.data(), count, stride, rings, sectors,
                          weights.data(), curves.data());
        disco::yaw_conf(queries.data(), cands.data(), count, stride, rings, sectors,
                        weights.data(), 2, yaws.data(), confs.data());
        return hash_of(confs, hash_of(yaws, hash_of(curves, hash_of(scores))));
    });
    double err = 0.0;
    for (int v = 0; v < views; ++v)
        for (int k = 0; k < count; ++k)
            err = std::max(err, std::abs(scores[v * count + k] -
                                         reference_aligned(&queries[v * cells], at[k], rings, sectors)));
    expect(err < 1e-5, "aligned_correlations far from the reference");
    expect(scores[count + 4] > 0.9999f && scores[5] > 0.9999f && scores[9] == 0.0f &&
               scores[count + 9] == 0.0f,
           "aligned_correlations: 1 for a turned copy, 0 for a flat image");
    // The curve of a turned copy peaks at its turn, 11 sectors of 6 degrees either way.
    const float* c5 = &curves[5 * sectors];
    const auto peak = std::max_element(c5, c5 + sectors) - c5;
    expect((peak == 11 || peak == sectors - 11) && std::abs(std::abs(yaws[5]) - 66.0f) < 1e-3f &&
               confs[5] > 0.0f,
           "yaw curve and yaw_conf at the turn");
    std::printf("sector_correlation           pairs %d yaw %a hash %016llx\n", views * count,
                static_cast<double>(yaws[5]), reported(h));
    float d[8] = {};
    expect_throw<std::invalid_argument>("aligned_correlations, 0 rings", [&] {
        disco::aligned_correlations(d, 1, d, 1, 1, 0, 1, d);
    });
    expect_throw<std::invalid_argument>("aligned_correlations, 0 sectors", [&] {
        disco::aligned_correlations(d, 1, d, 1, 1, 1, 0, d);
    });
    expect_throw<std::invalid_argument>("aligned_correlations, stride -1", [&] {
        disco::aligned_correlations(d, 1, d, 1, -1, 1, 1, d);
    });
    expect_throw<std::invalid_argument>("aligned_correlations, -1 views", [&] {
        disco::aligned_correlations(d, -1, d, 1, 1, 1, 1, d);
    });
    expect_throw<std::invalid_argument>("yaw_curves, sectors past 2^20", [&] {
        disco::yaw_curves(d, d, 0, 0, 1, (1 << 20) + 1, d, d);
    });
    expect_throw<std::invalid_argument>("yaw_conf, -1 matches", [&] {
        disco::yaw_conf(d, d, -1, 0, 1, 4, d, 1, d, d);
    });
}

// ---- recentre_places and recentre_curves ----
void check_recentre() {
    const int rings = 6, sectors = 24, rows = rings + 2, width = sectors + 3, views = 3;
    const std::int64_t rp = 16;
    const std::vector<float> padded = random_floats(41, rows * width, 0, 3);
    std::vector<float> quads((rows - 1) * (width - 1) * 4);
    disco::recentre_table(padded.data(), rows, width, quads.data());
    const disco::RecentreImage image{quads.data(), rows, width, rings, sectors, rp};
    // Places through recentre_places, from cells' centres and positions (sector-major).
    std::vector<float> cx(rings * sectors), cy(rings * sectors);
    for (int s = 0; s < sectors; ++s)
        for (int r = 0; r < rings; ++r) {
            const double a = 2.0 * kPi * (s + 0.5) / sectors, d = 2.0 * (r + 0.5);
            cx[s * rings + r] = static_cast<float>(d * std::cos(a));
            cy[s * rings + r] = static_cast<float>(d * std::sin(a));
        }
    const disco::PlacesGrid grid{cx.data(), cy.data(), rings * sectors,
                                 static_cast<float>(rings / 12.0), static_cast<float>(rings + 1),
                                 static_cast<float>(sectors / (2.0 * kPi)),
                                 static_cast<float>(sectors - 0.5)};
    const std::vector<float> positions = {0.0f, 0.0f, 0.75f, -0.5f, -1.25f, 2.0f};
    std::vector<float> places(views * 2 * rings * sectors);
    const std::uint64_t hp = at_every_level("recentre_places", [&] {
        disco::recentre_places(grid, positions.data(), views, places.data());
        return hash_of(places);
    });
    // Its atan2 against std::atan2 (within a float step of the sector), its ring exact.
    double sector_err = 0.0;
    bool rings_ok = true;
    for (int v = 0; v < views; ++v)
        for (int c = 0; c < rings * sectors; ++c) {
            const float x = cx[c] + positions[2 * v], y = cy[c] + positions[2 * v + 1];
            const float ring = std::min(std::sqrt(x * x + y * y) * grid.ring_scale + 0.5f, grid.ring_cap);
            rings_ok = rings_ok && places[(v * 2) * rings * sectors + c] == ring;
            const double sector = static_cast<float>(std::atan2(y, x)) * grid.sector_scale + grid.sector_shift;
            sector_err = std::max(sector_err, std::abs(places[(v * 2 + 1) * rings * sectors + c] - sector));
        }
    expect(rings_ok && sector_err < 1e-5, "recentre_places far from its definition");
    std::printf("recentre_places              views %d hash %016llx\n", views, reported(hp));

    // recentre_curves reads within the table: clamp the places, as yaw_refine pads for.
    std::vector<const float*> ptrs;
    for (int v = 0; v < views; ++v) {
        float* p = &places[v * 2 * rings * sectors];
        for (int c = 0; c < rings * sectors; ++c) {
            p[c] = std::min(std::max(p[c], 0.0f), rows - 1.5f);
            p[rings * sectors + c] = std::min(std::max(p[rings * sectors + c], 0.0f), width - 1.5f);
        }
        ptrs.push_back(p);
    }
    const std::vector<float> match = random_floats(42, rings * sectors, 0, 3);
    std::vector<float> weights(rings);
    for (int r = 0; r < rings; ++r) weights[r] = 0.5f + 0.25f * r;
    std::vector<float> room(2 * (sectors / 2 + 1) * rp + 16);  // 64-byte aligned, as bindings_yaw
    float* spectrum = room.data() + (16 - reinterpret_cast<std::uintptr_t>(room.data()) / 4 % 16) % 16;
    std::vector<float> curves(views * sectors);
    std::vector<double> nccs(views);
    std::vector<float> match_sectors(rings * sectors);
    for (int r = 0; r < rings; ++r)
        for (int s = 0; s < sectors; ++s) match_sectors[s * rings + r] = match[r * sectors + s];
    const std::uint64_t hc = at_every_level("recentre_curves", [&] {
        disco::recentre_match(image, match.data(), spectrum);
        disco::recentre_curves(image, ptrs, spectrum, weights.data(), curves.data());
        for (int v = 0; v < views; ++v)
            nccs[v] = disco::recentre_ncc(image, ptrs[v], match_sectors.data(), v + 1);
        return hash_of(nccs, fnv1a(spectrum, 2 * (sectors / 2 + 1) * rp * sizeof(float), hash_of(curves)));
    });
    // Each view read by hand (bilinear, as polar_resample), then yaw_curves of it: the
    // same curve within rounding (rings summed in another order).
    double err = 0.0;
    for (int v = 0; v < views; ++v) {
        std::vector<float> view(rings * sectors), curve(sectors);
        for (int s = 0; s < sectors; ++s)
            for (int r = 0; r < rings; ++r) {
                const float rf = ptrs[v][s * rings + r], sf = ptrs[v][rings * sectors + s * rings + r];
                const int r0 = static_cast<int>(rf), s0 = static_cast<int>(sf);
                const double fr = rf - r0, fs = sf - s0;
                const float* p = &padded[r0 * width + s0];
                const double near = p[0] + (p[1] - p[0]) * fs;
                const double far = p[width] + (p[width + 1] - p[width]) * fs;
                view[r * sectors + s] = static_cast<float>(near + (far - near) * fr);
            }
        disco::yaw_curves(view.data(), match.data(), 1, 0, rings, sectors, weights.data(), curve.data());
        double peak = 0.0;
        for (float c : curve) peak = std::max(peak, static_cast<double>(std::abs(c)));
        for (int s = 0; s < sectors; ++s)
            err = std::max(err, std::abs(curves[v * sectors + s] - curve[s]) / peak);
    }
    expect(err < 1e-4, "recentre_curves far from yaw_curves of the views read by hand");
    std::printf("recentre_curves              views %d ncc %a hash %016llx\n", views, nccs[0],
                reported(hc));
    disco::RecentreImage odd = image;
    odd.rings_padded = 8;
    expect_throw<std::invalid_argument>("recentre_curves, rings_padded 8", [&] {
        disco::recentre_curves(odd, ptrs, spectrum, weights.data(), curves.data());
    });
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (int which : {0, 1})
        for (float bad : {-0.25f, which ? width - 1.0f : rows - 1.0f, nan, 3e9f}) {
            std::vector<float> p(ptrs[1], ptrs[1] + 2 * rings * sectors);
            p[which * rings * sectors + 17] = bad;
            const std::vector<const float*> one = {ptrs[0], p.data()};
            expect_throw<std::out_of_range>("recentre_curves, a place outside the table", [&] {
                disco::recentre_curves(image, one, spectrum, weights.data(), curves.data());
            });
        }
}

// ---- exact_search and projected_search ----
void check_searches() {
    const std::int64_t n = 200, d = 37, b = 3, m = 150;
    // Full float mantissas (divided by 3): the distances' sums round, so their order shows.
    std::vector<float> x = random_floats(51, n * d, -1, 1), q = random_floats(52, b * d, -1, 1);
    for (float& v : x) v /= 3.0f;
    for (float& v : q) v /= 3.0f;
    std::copy(x.begin() + 5 * d, x.begin() + 6 * d, x.begin() + 17 * d);  // rows 5, 17: a tie
    std::vector<std::int64_t> cand(b * m);
    Rng rng{53};
    for (std::int64_t i = 0; i < b; ++i) {
        std::vector<std::int64_t> rows(n);
        for (std::int64_t r = 0; r < n; ++r) rows[r] = r;
        for (std::int64_t r = n - 1; r > 0; --r) std::swap(rows[r], rows[rng.next() % (r + 1)]);
        for (std::int64_t j = 0; j < m; ++j) cand[i * m + j] = j % 11 == 3 ? -1 : rows[j];
        cand[i * m] = 5, cand[i * m + 1] = 17;
    }
    for (int k : {1, 10, 140, 200}) {  // 140 (136 given): padded with -1 and infinity
        std::vector<double> dist(m), sq_all;
        std::vector<std::int64_t> out_rows(b * k);
        std::vector<double> out_dists(b * k);
        const std::uint64_t h = at_every_level("exact_search k " + std::to_string(k), [&] {
            sq_all.clear();
            for (std::int64_t i = 0; i < b; ++i) {
                std::vector<std::int64_t> given;
                for (std::int64_t j = 0; j < m; ++j)
                    if (cand[i * m + j] >= 0) given.push_back(cand[i * m + j]);
                std::vector<double> sq(given.size());
                disco::exact_sq_distances(x.data(), d, &q[i * d], given.data(),
                                          static_cast<std::int64_t>(given.size()), sq.data());
                sq_all.insert(sq_all.end(), sq.begin(), sq.end());
            }
            disco::exact_topk(x.data(), d, q.data(), b, cand.data(), m, k, out_rows.data(),
                              out_dists.data());
            return hash_of(out_dists, hash_of(out_rows, hash_of(sq_all)));
        });
        // Distances against a plain sum in double, the top k against a full sort.
        std::size_t at = 0;
        bool ok = true;
        for (std::int64_t i = 0; i < b; ++i) {
            std::vector<std::pair<double, std::int64_t>> all;
            for (std::int64_t j = 0; j < m; ++j) {
                const std::int64_t r = cand[i * m + j];
                if (r < 0) continue;
                double ref = 0.0;
                for (std::int64_t t = 0; t < d; ++t) {
                    const double diff = static_cast<double>(x[r * d + t]) - q[i * d + t];
                    ref += diff * diff;
                }
                ok = ok && std::abs(sq_all[at] - ref) <= 1e-12 * ref;
                all.emplace_back(sq_all[at++], r);
            }
            std::sort(all.begin(), all.end());
            for (int j = 0; j < k; ++j) {
                const bool have = j < static_cast<int>(all.size());
                ok = ok && out_rows[i * k + j] == (have ? all[j].second : -1) &&
                     out_dists[i * k + j] == (have ? std::sqrt(all[j].first)
                                                   : std::numeric_limits<double>::infinity());
            }
        }
        expect(ok, "exact_search k " + std::to_string(k) + " differs from the reference");
        std::printf("exact_search k %-3d           queries %lld hash %016llx\n", k,
                    static_cast<long long>(b), reported(h));
    }

    // projected_approx: its definition, one fma per axis in order from zero, exactly.
    for (std::int64_t p : {1, 10, 33}) {
        const std::int64_t pn = 150, pb = 4, tiles = (pn + disco::kProjectedTile - 1) / disco::kProjectedTile;
        const std::vector<float> pt = random_floats(60 + p, p * pn, -2, 2);
        const std::vector<float> sq = random_floats(70 + p, pn, 0, 8);
        const std::vector<float> pq = random_floats(80 + p, pb * p, -2, 2);
        std::vector<float> tiled(tiles * p * disco::kProjectedTile, 0.0f);
        for (std::int64_t k = 0; k < p; ++k)
            for (std::int64_t j = 0; j < pn; ++j)
                tiled[(j / disco::kProjectedTile * p + k) * disco::kProjectedTile +
                      j % disco::kProjectedTile] = pt[k * pn + j];
        std::vector<float> out(pb * pn), ref(pb * pn);
        for (std::int64_t i = 0; i < pb; ++i)
            for (std::int64_t j = 0; j < pn; ++j) {
                float acc = 0.0f;
                for (std::int64_t k = 0; k < p; ++k) acc = std::fma(pq[i * p + k], pt[k * pn + j], acc);
                ref[i * pn + j] = sq[j] - 2.0f * acc;
            }
        const std::uint64_t h = at_every_level("projected_approx p " + std::to_string(p), [&] {
            disco::projected_approx(tiled.data(), p, pn, sq.data(), pq.data(), pb, out.data());
            expect(same_bits(out, ref), "projected_approx p " + std::to_string(p) + " at " +
                                            disco::projected_kernel_name() + " != its definition");
            return hash_of(out);
        });
        std::printf("projected_approx p %-3lld       rows %lld hash %016llx\n",
                    static_cast<long long>(p), static_cast<long long>(pn), reported(h));
    }
}

// ---- row_selection: against a full sort ----
void check_row_selection() {
    const std::int64_t b = 5, n = 1000;
    Rng rng{90};
    std::vector<float> values(b * n);
    const float inf = std::numeric_limits<float>::infinity();
    for (std::int64_t i = 0; i < b * n; ++i) {
        const std::uint64_t r = rng.next() % 100;
        // Many ties (eighths in [0, 4)), some excluded columns; row 4 mostly excluded.
        values[i] = r < 5 ? inf : r < 8 ? -inf : r < 11 ? std::numeric_limits<float>::quiet_NaN()
                                                          : static_cast<float>(rng.next() % 32) / 8.0f - 1.0f;
        if (i / n == 4 && i % n > 20) values[i] = inf;
    }
    int checked = 0;
    for (std::int64_t k : {0, 1, 7, 50, 999, 1003}) {
        std::vector<std::int64_t> out(b * k, -7);
        disco::smallest_per_row(values.data(), b, n, k, out.data());
        for (std::int64_t i = 0; i < b; ++i) {
            std::vector<std::pair<float, std::int64_t>> finite;
            for (std::int64_t j = 0; j < n; ++j)
                if (std::isfinite(values[i * n + j])) finite.emplace_back(values[i * n + j], j);
            std::sort(finite.begin(), finite.end());
            for (std::int64_t j = 0; j < k; ++j) {
                const std::int64_t want = j < static_cast<std::int64_t>(finite.size()) ? finite[j].second : -1;
                expect(out[i * k + j] == want, "smallest_per_row k " + std::to_string(k) +
                                                    " differs from a full sort");
                ++checked;
            }
        }
    }
    std::printf("smallest_per_row             entries %d\n", checked);
}

// ---- conv3x3: direct and Winograd against double precision ----
struct ConvCase {
    std::vector<std::int64_t> parts;
    std::int64_t cout, rings, sectors;
    bool circular, relu;
};

void check_conv() {
    const std::int64_t batch = 2;
    const std::vector<ConvCase> cases = {
        {{3, 2}, 11, 5, 15, true, true},  {{3, 2}, 11, 5, 15, false, false},
        {{16, 8}, 19, 7, 9, true, false}, {{16, 8}, 19, 7, 9, false, true},
        {{4}, 8, 1, 1, true, false},      {{1, 6}, 3, 2, 3, false, true},
        {{8, 8}, 16, 8, 16, true, true},
    };
    double worst[2] = {0.0, 0.0};
    int runs = 0;
    for (const ConvCase& cc : cases) {
        std::int64_t cin = 0;
        for (std::int64_t c : cc.parts) cin += c;
        const std::int64_t R = cc.rings, S = cc.sectors, img = batch * R * S;
        const std::vector<float> w = random_floats(100 + cin * cc.cout, cc.cout * cin * 9, -1, 1);
        const std::vector<float> bias = random_floats(200 + cc.cout, cc.cout, -1, 1);
        const std::vector<float> x = random_floats(300 + R * S, cin * img, -2, 2);
        std::vector<disco::ConvPart> parts;
        std::int64_t at = 0;
        for (std::int64_t c : cc.parts) parts.push_back({x.data() + at * img, c}), at += c;
        // The reference, and each output's sum of |terms| (the scale of its rounding).
        std::vector<double> ref(cc.cout * img), scale(cc.cout * img);
        for (std::int64_t o = 0; o < cc.cout; ++o)
            for (std::int64_t bb = 0; bb < batch; ++bb)
                for (std::int64_t r = 0; r < R; ++r)
                    for (std::int64_t s = 0; s < S; ++s) {
                        double sum = bias[o], abs_sum = std::abs(bias[o]);
                        for (std::int64_t c = 0; c < cin; ++c)
                            for (int dy = 0; dy < 3; ++dy)
                                for (int dx = 0; dx < 3; ++dx) {
                                    const std::int64_t rr = r + dy - 1;
                                    std::int64_t ss = s + dx - 1;
                                    if (rr < 0 || rr >= R) continue;
                                    if (ss < 0 || ss >= S) {
                                        if (!cc.circular) continue;
                                        ss = (ss + S) % S;
                                    }
                                    const double t = static_cast<double>(w[((o * cin + c) * 3 + dy) * 3 + dx]) *
                                                     x[((c * batch + bb) * R + rr) * S + ss];
                                    sum += t, abs_sum += std::abs(t);
                                }
                        const std::int64_t i = ((o * batch + bb) * R + r) * S + s;
                        ref[i] = cc.relu ? std::max(0.0, sum) : sum;
                        scale[i] = abs_sum;
                    }
        const disco::Conv3x3 conv(w.data(), bias.data(), cc.cout, cin);
        const std::string name = "conv3x3 " + std::to_string(R) + "x" + std::to_string(S) + " cin " +
                                 std::to_string(cin) + " cout " + std::to_string(cc.cout) +
                                 (cc.circular ? " circular" : " zero") + (cc.relu ? " relu" : "");
        std::string verdict;
        for (int a = 0; a < 2; ++a) {
            const auto algo = a == 0 ? disco::ConvAlgorithm::direct : disco::ConvAlgorithm::winograd;
            double err = 0.0;
            for (int level = disco::bev_kernel_level(); level >= 0; --level) {
                disco::set_bev_kernel_level(level);
                std::vector<float> out(cc.cout * img, std::numeric_limits<float>::quiet_NaN());
                conv.run(parts, batch, R, S, cc.circular, cc.relu, out.data(), algo);
                for (std::size_t i = 0; i < out.size(); ++i) {
                    const double e = std::abs(out[i] - ref[i]) / (scale[i] + 1e-30);
                    err = std::isnan(e) ? 1.0 : std::max(err, e);
                }
                if (cc.relu)
                    for (float v : out) expect(v >= 0.0f, name + ": relu left a negative value");
                ++runs;
            }
            disco::set_bev_kernel_level(3);
            worst[a] = std::max(worst[a], err);
            // float32 sums of at most 9 cin terms (and Winograd's transforms): well under 1e-5.
            expect(err < 1e-5, name + (a ? " winograd" : " direct") + ": far from the reference");
            verdict += std::string(a ? " winograd " : " direct ") + (err < 1e-5 ? "ok" : "FAIL");
        }
        std::printf("%-44s%s\n", name.c_str(), verdict.c_str());
    }
    // Rounding differs by level and platform (fused multiply-adds): kept out of the diff.
    std::printf("# conv3x3 largest error / sum of |terms|: direct %.1e winograd %.1e (%d runs)\n",
                worst[0], worst[1], runs);
    const float w[9] = {}, bias[1] = {};
    const float xs[16] = {};
    expect_throw<std::invalid_argument>("Conv3x3 with cout 0", [&] { (void)disco::Conv3x3(w, bias, 0, 1); });
    expect_throw<std::invalid_argument>("Conv3x3 with cin 0", [&] { (void)disco::Conv3x3(w, bias, 1, 0); });
    expect_throw<std::invalid_argument>("Conv3x3Winograd with cout 0",
                                        [&] { (void)disco::Conv3x3Winograd(w, bias, 0, 1); });
    expect_throw<std::invalid_argument>("Conv3x3Winograd with cin 0",
                                        [&] { (void)disco::Conv3x3Winograd(w, bias, 1, 0); });
    const disco::Conv3x3 one(w, bias, 1, 1);
    float out[16];
    for (auto algo : {disco::ConvAlgorithm::direct, disco::ConvAlgorithm::winograd,
                      disco::ConvAlgorithm::automatic}) {
        expect_throw<std::invalid_argument>("conv3x3 parts of 2 channels for cin 1", [&] {
            one.run({{xs, 1}, {xs, 1}}, 1, 2, 2, true, false, out, algo);
        });
        expect_throw<std::invalid_argument>("conv3x3 part of -1 channels", [&] {
            one.run({{xs, 2}, {xs, -1}}, 1, 2, 2, true, false, out, algo);
        });
        expect_throw<std::invalid_argument>("conv3x3 of -1 rings", [&] {
            one.run({{xs, 1}}, 1, -1, 2, true, false, out, algo);
        });
    }
}

}  // namespace

int check_kernels(std::uint64_t* checksum) {
    checksum_out = checksum;
    disco::set_bev_kernel_level(3);
    const int best = disco::bev_kernel_level();
    std::printf("# levels here: sector_fft lanes");
    for (int level = best; level >= 0; --level) {
        disco::set_bev_kernel_level(level);
        std::printf(" %d", disco::sector_fft_lanes(disco::sector_fft_level()));
    }
    std::printf(", exact/projected/conv");
    for (int level = best; level >= 0; --level) {
        disco::set_bev_kernel_level(level);
        std::printf(" %s/%s/%s", disco::exact_kernel_name(), disco::projected_kernel_name(),
                    disco::conv3x3_kernel_name(level));
    }
    disco::set_bev_kernel_level(3);
    std::printf(", winograd levels");
    for (int level = best; level >= 0; --level)
        std::printf(" %d", disco::winograd_level(level));
    std::printf("\n");
    check_sector_fft();
    check_sector_correlation();
    check_recentre();
    check_searches();
    check_row_selection();
    check_conv();
    return failures;
}

}  // namespace disco_check

// sphshot-vdb-points: spray particles as an OpenVDB PointDataGrid, which pyopenvdb 10 cannot write.
//
//   sphshot-vdb-points write IN OUT.vdb        IN (a file, or - for standard input): uint64 n, then
//                                              n x 3 float32 positions (m), n x 3 float32
//                                              velocities (m/s), n float32 radii (m), n int32
//                                              fluid indices, all little-endian; then reads the
//                                              file back and prints it as `read` does
//   sphshot-vdb-points read FILE.vdb           prints the grid `spray` as JSON: its point count and,
//                                              per attribute, sums and extremes (for checks)
//
// The grid is named `spray`; its attributes are `P`, `v` (velocity), `pscale` (radius) and `fluid`,
// the names Houdini's and Blender's VDB points read. Positions are stored uncompressed (no
// quantisation). The voxel size is OpenVDB's own choice for about 8 points a voxel. Built by
// scripts/setup.sh into .venv/bin; pipeline/formats.py runs it and publishes the file atomically.
// Exit codes: 0 done, 1 bad input or I/O error (one line on stderr), 2 usage.
#include <openvdb/openvdb.h>
#include <openvdb/points/PointConversion.h>
#include <openvdb/points/PointCount.h>
#include <openvdb/points/PointDataGrid.h>

#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <limits>
#include <string>
#include <vector>

using namespace openvdb;
using namespace openvdb::points;

namespace {

template <typename T>
bool read_block(std::istream& in, std::vector<T>& out, uint64_t count) {
    out.resize(count);
    in.read(reinterpret_cast<char*>(out.data()), static_cast<std::streamsize>(count * sizeof(T)));
    return static_cast<uint64_t>(in.gcount()) == count * sizeof(T);
}

template <typename T, typename IndexTreeT>
void add_attribute(PointDataGrid& grid, const IndexTreeT& index, const std::string& name, const std::vector<T>& values) {
    appendAttribute<T>(grid.tree(), name);
    PointAttributeVector<T> wrapper(values);
    populateAttribute<PointDataTree, IndexTreeT, PointAttributeVector<T>>(grid.tree(), index, name, wrapper);
}

// Why the .vdb file at `path` does not hold together, or "" if it does: the layout check of
// pipeline/formats.py's vdb_cut_short (every length and stream position against the file's size),
// run before OpenVDB opens the file. A file cut short by a full disk is written without an error,
// and OpenVDB reading one can take a string length from past its end and allocate gigabytes.
std::string cut_short(const std::string& path) {
    std::ifstream in(path, std::ios::binary | std::ios::ate);
    if (!in) return "it cannot be opened";
    const uint64_t size = static_cast<uint64_t>(in.tellg());
    in.seekg(0);
    uint64_t at = 0;
    auto take = [&](uint64_t n, void* out) {
        if (n > size - at) return false;
        if (out) in.read(static_cast<char*>(out), static_cast<std::streamsize>(n));
        else in.seekg(static_cast<std::streamoff>(n), std::ios::cur);
        at += n;
        return static_cast<bool>(in);
    };
    auto u32 = [&](uint32_t& v) { return take(4, &v); };
    auto string = [&]() { uint32_t n = 0; return u32(n) && take(n, nullptr); };
    const std::string past = "it ends inside its own layout (" + std::to_string(size) + " bytes)";
    int64_t magic = 0;
    char versions[12], offsets = 0, uuid[36];
    uint32_t count = 0;
    if (!take(8, &magic) || !take(12, versions) || !take(1, &offsets) || !take(36, uuid)) return past;
    if (magic != 0x56444220) return "no OpenVDB magic number";
    if (offsets != 1) return "written without grid offsets";
    if (!u32(count)) return past;
    for (uint32_t k = 0; k < count; ++k) {
        uint32_t n = 0;
        if (!string() || !string() || !u32(n) || !take(n, nullptr)) return past;
    }
    if (!u32(count)) return past;
    uint64_t end = at;
    for (uint32_t k = 0; k < count; ++k) {
        int64_t pos[3];
        if (!string() || !string() || !string() || !take(sizeof(pos), pos)) return past;
        if (!(static_cast<int64_t>(at) <= pos[0] && pos[0] <= pos[1] && pos[1] <= pos[2] &&
              static_cast<uint64_t>(pos[2]) <= size)) {
            return "grid " + std::to_string(k) + "'s data (bytes " + std::to_string(pos[0]) + " to " +
                   std::to_string(pos[2]) + ") does not lie within the file's " + std::to_string(size) + " bytes";
        }
        end = at = static_cast<uint64_t>(pos[2]);
        in.seekg(static_cast<std::streamoff>(at));
    }
    if (end != size) return std::to_string(size - end) + " bytes after the last grid";
    return "";
}

int read(const std::string& path) {
    const std::string why = cut_short(path);
    if (!why.empty()) {
        std::cerr << "sphshot-vdb-points: " << path << ": the file does not hold together: " << why << std::endl;
        return 1;
    }
    io::File file(path);
    file.open();
    GridBase::Ptr base = file.readGrid("spray");
    file.close();
    PointDataGrid::Ptr grid = gridPtrCast<PointDataGrid>(base);
    if (!grid) {
        std::cerr << "sphshot-vdb-points: " << path << ": the grid `spray` is not a PointDataGrid" << std::endl;
        return 1;
    }
    const Index64 n = pointCount(grid->tree());
    double p[3] = {0, 0, 0}, v[3] = {0, 0, 0}, pscale = 0, fluid = 0;
    double lo[3], hi[3];
    for (int k = 0; k < 3; ++k) { lo[k] = std::numeric_limits<double>::max(); hi[k] = -lo[k]; }
    for (auto leaf = grid->tree().cbeginLeaf(); leaf; ++leaf) {
        AttributeHandle<Vec3f> ph(leaf->constAttributeArray("P"));
        AttributeHandle<Vec3f> vh(leaf->constAttributeArray("v"));
        AttributeHandle<float> sh(leaf->constAttributeArray("pscale"));
        AttributeHandle<int32_t> fh(leaf->constAttributeArray("fluid"));
        for (auto it = leaf->beginIndexOn(); it; ++it) {
            const Vec3d world = grid->transform().indexToWorld(ph.get(*it) + it.getCoord().asVec3d());
            const Vec3f vel = vh.get(*it);
            for (int k = 0; k < 3; ++k) {
                p[k] += world[k];
                v[k] += vel[k];
                lo[k] = std::min(lo[k], world[k]);
                hi[k] = std::max(hi[k], world[k]);
            }
            pscale += sh.get(*it);
            fluid += fh.get(*it);
        }
    }
    std::printf("{\"count\": %llu, \"position_sum\": [%.9g, %.9g, %.9g], \"velocity_sum\": [%.9g, %.9g, %.9g], "
                "\"position_min\": [%.9g, %.9g, %.9g], \"position_max\": [%.9g, %.9g, %.9g], "
                "\"pscale_sum\": %.9g, \"fluid_sum\": %.9g}\n",
                static_cast<unsigned long long>(n), p[0], p[1], p[2], v[0], v[1], v[2],
                lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], pscale, fluid);
    return 0;
}

int write(const std::string& input, const std::string& output) {
    std::ifstream source;
    if (input != "-") source.open(input, std::ios::binary);
    std::istream& in = input == "-" ? std::cin : source;
    uint64_t n = 0;
    in.read(reinterpret_cast<char*>(&n), sizeof(n));
    std::vector<Vec3f> position, velocity;
    std::vector<float> radius;
    std::vector<int32_t> fluid;
    if (!in || !read_block(in, position, n) || !read_block(in, velocity, n) || !read_block(in, radius, n) ||
        !read_block(in, fluid, n)) {
        std::cerr << "sphshot-vdb-points: " << input << ": shorter than its point count says" << std::endl;
        return 1;
    }
    PointAttributeVector<Vec3f> positions(position);
    const float voxel = n > 0 ? computeVoxelSize(positions, 8) : 1.0f;
    math::Transform::Ptr xform = math::Transform::createLinearTransform(voxel);
    tools::PointIndexGrid::Ptr index = tools::createPointIndexGrid<tools::PointIndexGrid>(positions, *xform);
    PointDataGrid::Ptr grid = createPointDataGrid<NullCodec, PointDataGrid>(*index, positions, *xform);
    add_attribute(*grid, index->tree(), "v", velocity);
    add_attribute(*grid, index->tree(), "pscale", radius);
    add_attribute(*grid, index->tree(), "fluid", fluid);
    grid->setName("spray");
    io::File file(output);
    file.write(GridCPtrVec{grid});
    file.close();
    return read(output);        // what a reader of the file gets
}

}  // namespace

int main(int argc, char** argv) {
    const std::string mode = argc > 1 ? argv[1] : "";
    if (!((mode == "write" && argc == 4) || (mode == "read" && argc == 3))) {
        std::cerr << "usage: sphshot-vdb-points write IN|- OUT.vdb | read FILE.vdb" << std::endl;
        return 2;
    }
    openvdb::initialize();
    try {
        return mode == "write" ? write(argv[2], argv[3]) : read(argv[2]);
    } catch (const std::exception& exc) {
        std::string what = exc.what();          // OpenVDB's messages can quote what it read: keep one short line
        for (char& c : what) if (c == '\n' || c == '\r') c = ' ';
        if (what.size() > 200) what = what.substr(0, 200) + "...";
        std::cerr << "sphshot-vdb-points: " << what << std::endl;
        return 1;
    }
}

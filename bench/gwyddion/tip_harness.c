/* Minimal harness around Gwyddion's tip morphology (libgwyprocess), for bench/bench_tip.py.
 *
 * Usage:
 *   tip_harness IMAGE WIDTH HEIGHT XREAL YREAL estimate-full TIP_N THRESHOLD_M OUT [USE_EDGES]
 *   tip_harness IMAGE WIDTH HEIGHT XREAL YREAL dilate TIPFILE TIP_N OUT
 *   tip_harness IMAGE WIDTH HEIGHT XREAL YREAL erode  TIPFILE TIP_N OUT
 *
 * IMAGE, TIPFILE and OUT are raw little-endian float64, row-major (x fastest), which is
 * GwyDataField's own layout (data[col + xres*row]) and numpy's C order for an array
 * indexed [row, col]. XREAL/YREAL are the image's physical sizes in metres; a tip field of
 * TIP_N x TIP_N pixels gets the same pixel size. THRESHOLD_M is in metres (Gwyddion turns it
 * into an integer number of height steps, step = image range / 10000, by truncation).
 * USE_EDGES defaults to 1: the "Use boundaries" default of Gwyddion 2.62's Blind Estimation
 * dialog (modules/tip/tip_blind.c, PARAM_USE_BOUNDARIES = TRUE).
 *
 * estimate-full starts from an all-zero tip field, as the GUI does after "Reset Tip" or a size
 * change, and writes the estimate exactly as Gwyddion returns it (apex = maximum, min = 0).
 * dilate/erode take the tip in Gwyddion's convention (apex = maximum) and write the result.
 *
 * Prints one JSON object on stdout; "seconds" is the wall time of the Gwyddion call alone
 * (g_get_monotonic_time); "vm_hwm_kib" the process's peak resident memory (VmHWM of
 * /proc/self/status, -1 where unreadable; the parent's getrusage of children would count the
 * parent's pages shared before exec). Threads are disabled (gwy_threads_set_enabled(FALSE) and one
 * OpenMP thread), matching the single-threaded reference measurement.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <omp.h>
#include <glib.h>
#include <libgwyddion/gwyddion.h>
#include <libprocess/datafield.h>
#include <libprocess/stats.h>
#include <libprocess/tip.h>

static void
die(const gchar *message)
{
    fprintf(stderr, "tip_harness: %s\n", message);
    exit(2);
}

static long
vm_hwm_kib(void)
{
    char line[256];
    long kib = -1;
    FILE *fh = fopen("/proc/self/status", "r");
    if (!fh)
        return -1;
    while (fgets(line, sizeof line, fh))
        if (strncmp(line, "VmHWM:", 6) == 0)
            kib = strtol(line + 6, NULL, 10);
    fclose(fh);
    return kib;
}

static void
read_raw(const gchar *path, gdouble *data, gsize n)
{
    FILE *fh = fopen(path, "rb");
    if (!fh)
        die("cannot open input file");
    if (fread(data, sizeof(gdouble), n, fh) != n)
        die("input file too short");
    if (fgetc(fh) != EOF)
        die("input file too long for the given size");
    fclose(fh);
}

static void
write_raw(const gchar *path, const gdouble *data, gsize n)
{
    FILE *fh = fopen(path, "wb");
    if (!fh || fwrite(data, sizeof(gdouble), n, fh) != n || fclose(fh) != 0)
        die("cannot write output file");
}

static GwyDataField*
load_field(const gchar *path, gint xres, gint yres, gdouble xreal, gdouble yreal)
{
    GwyDataField *field = gwy_data_field_new(xres, yres, xreal, yreal, FALSE);
    read_raw(path, gwy_data_field_get_data(field), (gsize)xres*yres);
    gwy_data_field_invalidate(field);
    return field;
}

static gint
parse_int(const gchar *s)
{
    gchar *end;
    glong v = strtol(s, &end, 10);
    if (*end || v <= 0)
        die("expected a positive integer");
    return (gint)v;
}

static gdouble
parse_double(const gchar *s)
{
    gchar *end;
    gdouble v = g_ascii_strtod(s, &end);
    if (*end)
        die("expected a number");
    return v;
}

int
main(int argc, char *argv[])
{
    GwyDataField *surface, *tip, *result;
    gint xres, yres, tip_n, count = -1;
    gdouble xreal, yreal, dx, dy, threshold, step, min, max, seconds;
    gint64 t0, t1;
    const gchar *mode;

    if (argc < 7)
        die("usage: tip_harness IMAGE WIDTH HEIGHT XREAL YREAL "
            "(estimate-full TIP_N THRESHOLD_M OUT [USE_EDGES] | dilate TIPFILE TIP_N OUT | "
            "erode TIPFILE TIP_N OUT)");

    gwy_threads_set_enabled(FALSE);
    omp_set_num_threads(1);
    gwy_type_init();

    xres = parse_int(argv[2]);
    yres = parse_int(argv[3]);
    xreal = parse_double(argv[4]);
    yreal = parse_double(argv[5]);
    mode = argv[6];
    surface = load_field(argv[1], xres, yres, xreal, yreal);
    dx = xreal/xres;
    dy = yreal/yres;
    min = gwy_data_field_get_min(surface);
    max = gwy_data_field_get_max(surface);
    step = (max - min)/10000.0;

    if (strcmp(mode, "estimate-full") == 0) {
        gboolean use_edges = TRUE;
        if (argc != 10 && argc != 11)
            die("estimate-full TIP_N THRESHOLD_M OUT [USE_EDGES]");
        tip_n = parse_int(argv[7]);
        threshold = parse_double(argv[8]);
        if (argc == 11)
            use_edges = (strcmp(argv[10], "0") != 0);
        tip = gwy_data_field_new(tip_n, tip_n, tip_n*dx, tip_n*dy, TRUE);
        t0 = g_get_monotonic_time();
        result = gwy_tip_estimate_full(tip, surface, threshold, use_edges, &count, NULL, NULL);
        t1 = g_get_monotonic_time();
        if (!result)
            die("gwy_tip_estimate_full returned NULL");
        write_raw(argv[9], gwy_data_field_get_data_const(result), (gsize)tip_n*tip_n);
        seconds = (t1 - t0)/1e6;
        printf("{\"mode\": \"estimate-full\", \"seconds\": %.6f, \"tip_n\": %d, \"threshold_m\": %.17g, "
               "\"threshold_steps\": %d, \"step_m\": %.17g, \"use_edges\": %s, \"count\": %d, "
               "\"omp_max_threads\": %d, \"gwy_threads\": %s, \"vm_hwm_kib\": %ld}\n",
               seconds, tip_n, threshold, (gint)(threshold/step), step, use_edges ? "true" : "false",
               count, omp_get_max_threads(), gwy_threads_are_enabled() ? "true" : "false",
               vm_hwm_kib());
        g_object_unref(tip);
    }
    else if (strcmp(mode, "dilate") == 0 || strcmp(mode, "erode") == 0) {
        gboolean dilate = (strcmp(mode, "dilate") == 0);
        if (argc != 10)
            die("dilate|erode TIPFILE TIP_N OUT");
        tip_n = parse_int(argv[8]);
        tip = load_field(argv[7], tip_n, tip_n, tip_n*dx, tip_n*dy);
        result = gwy_data_field_new_alike(surface, FALSE);
        t0 = g_get_monotonic_time();
        if (dilate)
            result = gwy_tip_dilation(tip, surface, result, NULL, NULL);
        else
            result = gwy_tip_erosion(tip, surface, result, NULL, NULL);
        t1 = g_get_monotonic_time();
        if (!result)
            die("gwy_tip_dilation/erosion returned NULL");
        write_raw(argv[9], gwy_data_field_get_data_const(result), (gsize)xres*yres);
        seconds = (t1 - t0)/1e6;
        printf("{\"mode\": \"%s\", \"seconds\": %.6f, \"tip_n\": %d, \"omp_max_threads\": %d, "
               "\"gwy_threads\": %s, \"vm_hwm_kib\": %ld}\n",
               mode, seconds, tip_n, omp_get_max_threads(), gwy_threads_are_enabled() ? "true" : "false",
               vm_hwm_kib());
        g_object_unref(result);
        g_object_unref(tip);
    }
    else
        die("unknown mode (estimate-full, dilate, erode)");

    g_object_unref(surface);
    return 0;
}
